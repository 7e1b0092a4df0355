"""The status stage: whether the model could serve a scan, from its flags (:func:`unserved_reason`)."""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from mpi_lidar.correction.options import AUTO, MODEL_FLAGS, CorrectionOptions, Flag, UnservedReason
from mpi_lidar.correction.outcome import Unserved
from mpi_lidar.correction.result import code_counts

# A scene saturates where it is near and bright; amplitudes in a unit larger than the model's saturate nearly
# everywhere. Above this share of the pixels with a measurement, a scan is unserved for its amplitude units.
SATURATED_UNITS_SHARE = 0.9
# Above this share of the pixels with a measurement ambiguous in range, the scan is unserved for it.
AMBIGUOUS_SHARE = 0.5


def unserved_reason(flags: NDArray[np.uint8], d_as_m: tuple[float, float], options: CorrectionOptions,
                    served: bool = True) -> Unserved | None:
    """Why a model of range ``d_as_m`` [m] could not serve a scan of these ``flags`` (H*W,), or None where it could.

    ``served`` False: the model takes geometric inputs and the scan has none. Saturation in more than
    :data:`SATURATED_UNITS_SHARE` of the measured pixels reads as amplitudes in another unit; no corrected pixel while
    some pixels that may need correction were out of the model's range, as a range it was not trained for.
    """
    counts = code_counts(flags, len(Flag))
    measured = max(int(flags.size - counts[Flag.NOT_FINITE]), 1)
    low, high = d_as_m
    if counts[Flag.SATURATED] / measured > SATURATED_UNITS_SHARE:
        return Unserved(UnservedReason.AMPLITUDE_UNITS,
                        f"{100 * counts[Flag.SATURATED] / measured:.0f} % of the pixels read as saturated: the "
                        "amplitudes are clipped nearly everywhere (a scanner's gain, or a threshold in another unit); "
                        + unit_hint(options, "and saturation level"))
    if not served:
        return Unserved(UnservedReason.NO_GEOMETRY,
                        "the model takes geometric inputs and the scan has no geometry: import the scan with its "
                        "azimuth and elevation (mpi-lidar import-scan), or train a model without them "
                        "(mpi-lidar train --no-geometric)")
    if counts[Flag.AMBIGUOUS] / measured > AMBIGUOUS_SHARE:
        return Unserved(UnservedReason.AMBIGUOUS_RANGE,
                        f"{100 * counts[Flag.AMBIGUOUS] / measured:.0f} % of the pixels have an ambiguous range: "
                        "their frequencies' wrap counts cannot be told apart at their noise; if the scanner "
                        "unwrapped its depths already, import them so (mpi-lidar import-scan --depths unwrapped)")
    if sum(counts[flag] for flag in MODEL_FLAGS) == 0 and counts[Flag.OUT_OF_RANGE] > 0:
        return Unserved(UnservedReason.OUT_OF_RANGE,
                        f"{counts[Flag.OUT_OF_RANGE]:,} pixels that may need correction lie outside the model's "
                        f"range ({low:g}-{high:g} m) and none inside it: train a model for the scan's range "
                        "(mpi-lidar pipeline --config with prior.d_as_m set)")
    return None


def untrusted_unit(evidence: str, options: CorrectionOptions | None = None) -> Unserved:
    """A scan whose own evidence contradicts the V^2 its amplitudes were assumed in (``evidence``): the model does
    not read them; its fused depths are still written."""
    return Unserved(UnservedReason.AMPLITUDE_UNITS,
                    f"the model was not applied: {evidence}; {unit_hint(options or CorrectionOptions())}; the fused "
                    "depths are written")


def unit_hint(options: CorrectionOptions, what: str = "") -> str:
    """What to do about amplitudes in a unit the correction cannot use, by what the options already gave: a
    sensor profile (``--sensor``), a unit (``--amplitude-scale``), or neither. ``what``: more the scanner's unit
    should come with (``"and saturation level"``)."""
    more = f" {what}" if what else ""
    if options.sensor_profile_sha256 is not None:
        return ("the sensor profile given (--sensor) does not fit this scan: check it was calibrated on this "
                "scanner at these settings (gain, integration time), calibrate one on this scan's sensor "
                "(mpi-lidar calibrate), or override its unit with --amplitude-scale")
    if options.amplitude_scale != AUTO:
        return (f"the unit given (--amplitude-scale {options.amplitude_scale:g} per V^2) does not fit this scan: "
                f"check the scanner's unit per V^2{more}, or calibrate a profile (mpi-lidar calibrate, then "
                "--sensor sensor.toml)")
    return (f"give the scanner's unit per V^2{more} (a profile from mpi-lidar calibrate: --sensor sensor.toml, or "
            "mpi-lidar correct --amplitude-scale)")
