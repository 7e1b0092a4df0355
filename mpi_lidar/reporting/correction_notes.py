"""What a scan's report says of its correction in words, from the stages' results (:func:`correction_notes`)."""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from mpi_lidar.correction.amplitude_unit import V2_TOLERANCE, AmplitudeUnit, reads_as_v2
from mpi_lidar.correction.baseline import MIN_OFFSET_PIXELS, FrequencyOffsets, OffsetSource
from mpi_lidar.correction.footprint import FootprintEstimate
from mpi_lidar.correction.result import Correction


def correction_notes(correction: Correction) -> tuple[str, ...]:
    """The report's notes of one correction, in the stages' order: amplitude unit, scene geometry, footprint,
    the training prior's reach, frequency offsets."""
    notes: list[str] = []
    if correction.amplitude_unit is not None:
        notes.append(unit_note(correction.amplitude_unit))
    notes.extend(correction.scene_notes)
    calibration = correction.calibration
    if calibration is not None and calibration.pixels > 0:  # nothing to say where nothing faces
        notes.append(calibration_note(calibration, correction.uncalibrated_pixels))
    if correction.beyond_prior_pixels and correction.prior_reach is not None:
        notes.append(beyond_prior_note(correction.beyond_prior_pixels, correction.prior_reach))
    offsets = offsets_note(correction.offsets)
    return (*notes, *(() if offsets is None else (offsets,)))


def unit_note(unit: AmplitudeUnit) -> str:
    """What a report says of a scan's own amplitude unit."""
    if not unit.significant:
        return f"amplitude unit auto: not measured ({unit.reason}); every pixel left as measured"
    measured = (f"amplitude unit auto: {unit.amplitude_scale:.4g} +- {unit.relative_sigma * unit.amplitude_scale:.2g}"
                f" per V^2 from the scatter of the frequencies on {unit.pixels:,} pixels")
    if reads_as_v2(unit):
        return f"{measured}, within a factor {V2_TOLERANCE:g} of V^2: read as V^2"
    return f"{measured}; amplitudes divided by it"


def calibration_note(estimate: FootprintEstimate, uncalibrated: int) -> str:
    """What a report says of a scan's own footprint estimate and of the ``uncalibrated`` pixels it decided."""
    if not np.isfinite(estimate.area_m2):
        return (f"footprint auto: could not be measured on the {estimate.pixels:,} pixels with facing partners, "
                f"not significant: {uncalibrated:,} pixels that could hold multipath above the gate's threshold "
                "were not corrected (flag uncalibrated)")
    measured = (f"footprint auto: {estimate.area_m2:.4g} +- {estimate.sigma_m2:.2g} m^2 from {estimate.pixels:,} "
                f"pixels on {estimate.surfaces} surfaces")
    if estimate.significant:
        return f"{measured}; the coupling and the gate use it"
    return (f"{measured}, not significant: {uncalibrated:,} pixels that could hold multipath above the gate's "
            "threshold were not corrected (flag uncalibrated)")


def beyond_prior_note(beyond: int, reach: tuple[float, float]) -> str:
    """What a report says of the ``beyond`` corrected pixels whose multipath lies past ``reach``, the largest
    rho_ABA [1] and d_AB [m] of the model's training prior."""
    return (f"{beyond:,} corrected pixels have multipath beyond what the model was trained on (rho_ABA above "
            f"{reach[0]:g} or d_AB above {reach[1]:g} m, from the scene geometry): the model extrapolates there, "
            "and their uncertainty may be too small")


def offsets_mm(offsets_m: NDArray | tuple[float, ...]) -> str:
    """The frequencies' offsets [m] as a report lists them: millimetres, signed, comma-separated."""
    return ", ".join(f"{1e3 * o:+.3f}" for o in offsets_m)


def offsets_note(offsets: FrequencyOffsets) -> str | None:
    """What a report says of the frequency offsets the fused depths removed (None: nothing to say)."""
    if offsets.source == OffsetSource.NO_GEOMETRY:
        return ("frequency offsets: not measured (no scene geometry to find pixels free of multipath); "
                "none removed from the fused depths")
    if offsets.source == OffsetSource.TOO_FEW_PIXELS:
        return (f"frequency offsets: not measured (fewer than {MIN_OFFSET_PIXELS} sampled pixels free "
                "of multipath); none removed from the fused depths")
    if offsets.source != OffsetSource.MEASURED or offsets.offsets_m is None or offsets.other_m is None:
        return None
    leakage = "removed first" if offsets.window else "left in"
    return (f"frequency offsets: {offsets_mm(offsets.offsets_m)} mm relative to the highest frequency, measured on "
            f"the pixels free of multipath, removed from the fused depths; the integration window's leakage "
            f"{leakage} (the offsets would be {offsets_mm(offsets.other_m)} mm otherwise)")
