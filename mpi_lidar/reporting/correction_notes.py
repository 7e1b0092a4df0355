"""What a scan's report says of its correction in words, from the stages' results (:func:`correction_notes`)."""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from mpi_lidar.correction.baseline import MIN_OFFSET_PIXELS, FrequencyOffsets, OffsetSource
from mpi_lidar.correction.footprint import FootprintEstimate
from mpi_lidar.correction.result import Correction
from mpi_lidar.correction.sensor_reading import SensorReading

# The footprint's depth and amplitude estimates this far apart (the larger over the smaller) get a word in the
# report: beyond the depth's own 25 % systematic share. On the project's renders they agree within 1.15x; path
# traced, a strong 90-degree corner's were 1.5x apart and the joined estimate 1.34x the truth
# (docs/results/path-traced.md).
NOTED_DISAGREEMENT = 1.25


def correction_notes(correction: Correction) -> tuple[str, ...]:
    """The report's notes of one correction, in the stages' order: the sensor reading (noise law, unit), scene
    geometry, footprint, the training prior's reach, frequency offsets."""
    notes: list[str] = []
    if correction.reading is not None:
        notes.extend(reading_notes(correction.reading))
    notes.extend(correction.scene_notes)
    calibration = correction.calibration
    if calibration is not None and calibration.pixels > 0:  # nothing to say where nothing faces
        notes.append(calibration_note(calibration, correction.uncalibrated_pixels))
    if correction.beyond_prior_pixels and correction.prior_reach is not None:
        notes.append(beyond_prior_note(correction.beyond_prior_pixels, correction.prior_reach))
    offsets = offsets_note(correction.offsets)
    return (*notes, *(() if offsets is None else (offsets,)))


def reading_notes(reading: SensorReading) -> tuple[str, ...]:
    """What a report says of the scan's own noise law and amplitude unit."""
    law = reading.law
    if law is not None and law.significant:
        measured = (f"noise law: measured on {law.pixels:,} pixels from the scatter of the frequencies, read noise "
                    f"{law.read_scale:.3g} +- {law.read_sigma:.2g} and shot noise {law.shot_scale:.3g} +- "
                    f"{law.shot_sigma:.2g} times the sensor model's (in V^2 after the amplitude unit)")
    else:
        why = "no pixels" if law is None else law.reason
        measured = f"noise law: not measured ({why}); the sensor model's is used"
    if reading.disagrees_with_reference:
        measured += (f"; it is {reading.noise_over_reference:.2g} times the sensor model's noise (a profile's noise "
                     "scale included), which the scan's own law replaces")
    if reading.unit_given:
        unit = f"amplitude unit: {reading.units_per_v2:g} per V^2, as given"
    elif reading.unit_contradiction:
        unit = f"amplitude unit: not V^2 ({reading.unit_contradiction}); the model was not applied"
    else:
        unit = "amplitude unit: V^2 (not given; nothing in the scan contradicts it)"
    return measured, unit


def calibration_note(estimate: FootprintEstimate, uncalibrated: int) -> str:
    """What a report says of a scan's own footprint estimate and of the ``uncalibrated`` pixels it decided."""
    if not np.isfinite(estimate.area_m2):
        return (f"footprint auto: could not be measured on the {estimate.pixels:,} pixels with facing partners, "
                f"not significant: {uncalibrated:,} pixels that could hold multipath above the gate's threshold "
                "were not corrected (flag uncalibrated)")
    measured = (f"footprint auto: {estimate.area_m2:.4g} +- {estimate.sigma_m2:.2g} m^2 from {estimate.pixels:,} "
                f"pixels on {estimate.surfaces} surfaces")
    if estimate.significant and estimate.white_surfaces:
        return (f"{measured}, taken as white: the amplitude unit is not known, so this is the footprint times the "
                "albedos the light returns from; it sets only the uncertainty of the depths left alone")
    if estimate.significant:
        return f"{measured}; the coupling and the gate use it{disagreement_words(estimate)}"
    return (f"{measured}, not significant: {uncalibrated:,} pixels that could hold multipath above the gate's "
            "threshold were not corrected (flag uncalibrated)")


def disagreement_words(estimate: FootprintEstimate) -> str:
    """What a report adds where the depth's and the amplitude's estimates of the footprint lie
    :data:`NOTED_DISAGREEMENT` or more apart (nothing otherwise)."""
    apart = estimate.disagreement
    if not apart >= NOTED_DISAGREEMENT:
        return ""
    return (f"; its depth and amplitude measured {estimate.depth_m2:.3g} and {estimate.amplitude_m2:.3g} m^2, "
            f"{apart:.2g}x apart: the footprint, and the correction near edges, may be off by as much")


def beyond_prior_note(beyond: int, reach: tuple[float, float]) -> str:
    """What a report says of the ``beyond`` corrected pixels whose multipath lies past ``reach``, the largest
    rho_ABA [1] and d_AB [m] of the model's training prior."""
    return (f"{beyond:,} corrected pixels have multipath beyond what the model was trained on (rho_ABA above "
            f"{reach[0]:g} or d_AB above {reach[1]:g} m, from the scene geometry; flag beyond_prior): the model "
            "extrapolates there, and their uncertainty adds the share of the correction the prior leaves out")


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
