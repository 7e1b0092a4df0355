"""The baseline: what a valid pixel the model does not correct gets, its frequencies' depths fused by inverse
variance (less the frequencies' offsets) where they agree within noise, or the highest frequency's as measured.

:func:`frequency_offsets` measures the offsets once per scan, before the second pass; :func:`fuse_rows` fuses a
tile's rows in it.
"""

from __future__ import annotations

from dataclasses import dataclass
from enum import StrEnum

import numpy as np
from numpy.typing import NDArray

from mpi_lidar.correction.options import Baseline, CorrectionOptions, Flag
from mpi_lidar.correction.validity import OffsetSample
from mpi_lidar.errors import MpiLidarError
from mpi_lidar.physics.coupling import DEFAULT_FOOTPRINT_AREA_M2
from mpi_lidar.physics.noise import Fused, NoiseModel
from mpi_lidar.scans.geometry import FacingBlocks

# Valid pixels the model leaves alone, whose depth is the baseline's: fused where the frequencies agree.
BASELINE_FLAGS = (Flag.NOT_NEEDED, Flag.NO_MULTIPATH, Flag.UNCALIBRATED, Flag.OUT_OF_RANGE)
# The offsets are measured only with at least this many sampled pixels free of multipath (else none is removed).
MIN_OFFSET_PIXELS = 500
# A pixel is free of multipath for the offsets where the scene geometry, with white partners and the default
# footprint, expects a bias below this [m]: from the geometry alone, so that the same pixels are picked whatever
# the amplitudes' unit and whether the scan's own footprint estimate is significant.
QUIET_BIAS_M = 2e-5


# The options that hold one value per frequency of the scan, highest last as the scan orders them (a sensor
# profile's): each must have as many values as the scan has frequencies.
PER_FREQUENCY_OPTIONS = ("frequency_offsets_m",)


def check_per_frequency(options: CorrectionOptions, frequencies_hz: tuple[float, ...], where: str) -> None:
    """Refuse options that give another number of values than ``where`` (a scan) has frequencies [Hz], in any of
    :data:`PER_FREQUENCY_OPTIONS`, with one line, before any stage reads them."""
    for name in PER_FREQUENCY_OPTIONS:
        values = getattr(options, name)
        if values is not None and len(values) != len(frequencies_hz):
            mhz = ", ".join(f"{f / 1e6:g}" for f in frequencies_hz)
            raise MpiLidarError(f"the correction options give {len(values)} {name} for the {len(frequencies_hz)} "
                                f"frequencies of {where} ({mhz} MHz): a sensor profile of another sensor or "
                                "frequency set; give one value per frequency, or calibrate the sensor on such scans "
                                "(mpi-lidar calibrate)")


class OffsetSource(StrEnum):
    """Where a scan's frequency offsets came from."""

    NOTHING_FUSED = "nothing fused"  # the raw baseline: no offsets needed
    PROFILE = "profile"  # the options' (a sensor profile's)
    MEASURED = "measured"  # the scan's own pixels free of multipath
    NO_GEOMETRY = "no geometry"  # not measured: no scene geometry to find pixels free of multipath
    TOO_FEW_PIXELS = "too few pixels"  # not measured: fewer than MIN_OFFSET_PIXELS sampled pixels free of it


@dataclass(frozen=True)
class FrequencyOffsets:
    """What the fused depths remove from each frequency's depth (:func:`frequency_offsets`).

    offsets_m : Each frequency's offset relative to the highest (F,) (None: none). [m]
    window : Whether the integration window's leakage is removed first
        (:func:`~mpi_lidar.physics.window.window_corrections_m`).
    source : Where the offsets came from.
    other_m : The offsets measured the other way (with the leakage left in where ``window``, else removed), for
        the report (None unless measured). [m]
    """

    offsets_m: NDArray[np.float64] | None = None
    window: bool = False
    source: OffsetSource = OffsetSource.NOTHING_FUSED
    other_m: NDArray[np.float64] | None = None


def frequency_offsets(sample: OffsetSample, flags: NDArray[np.uint8], blocks: FacingBlocks | None,
                      options: CorrectionOptions) -> FrequencyOffsets:
    """What the fused depths remove: the options' (a sensor profile's) offsets where they give them, else the scan's
    own, measured on the sampled valid pixels (``sample``, of the validity pass) that the gate leaves to the baseline
    (``flags`` (H*W,), after the gate) and the scene geometry (``blocks``) expects free of multipath
    (:data:`QUIET_BIAS_M`); nothing where it has too few such pixels or no geometry.

    The scan also says whether its sensor has the default window's leakage: the leakage is removed where that
    leaves the frequencies' measured offsets smaller (in sum of squares) than it finds them. A sensor with it
    shows the leakage's differences between frequencies as offsets; removing it where a sensor has none would
    show them, reversed.
    """
    if Baseline(options.baseline) == Baseline.RAW:
        return FrequencyOffsets()
    if options.frequency_offsets_m is not None:  # a profile's, measured with the leakage removed or not
        return FrequencyOffsets(np.asarray(options.frequency_offsets_m, dtype=np.float64),
                                bool(options.window_leakage_removed), OffsetSource.PROFILE)
    if blocks is None:
        return FrequencyOffsets(source=OffsetSource.NO_GEOMETRY)
    stride = sample.stride  # only the sampled pixels: no mask of the whole scan
    quiet = np.isin(flags[::stride], [int(flag) for flag in BASELINE_FLAGS])
    sampled = np.arange(0, flags.size, stride)
    quiet &= blocks.block_potential(DEFAULT_FOOTPRINT_AREA_M2).pixels(sampled).bias_m <= QUIET_BIAS_M
    as_measured = _median_offsets(sample.differences, quiet)
    if as_measured is None:
        return FrequencyOffsets(source=OffsetSource.TOO_FEW_PIXELS)
    windowed = _median_offsets(sample.window_differences, quiet)
    assert windowed is not None  # the same pixels
    window = bool(np.sum(windowed**2) < np.sum(as_measured**2))
    offsets, other = (windowed, as_measured) if window else (as_measured, windowed)
    return FrequencyOffsets(offsets, window, OffsetSource.MEASURED, other)


def _median_offsets(differences: NDArray, quiet: NDArray[np.bool_]) -> NDArray[np.float64] | None:
    """The median difference of each frequency (F,) [m] over the sampled pixels that are ``quiet``, or None with
    fewer than ``MIN_OFFSET_PIXELS`` of them."""
    taken = quiet & np.isfinite(differences).all(1)
    if taken.sum() < MIN_OFFSET_PIXELS:
        return None
    return np.median(differences[taken].astype(np.float64), axis=0)


def fuse_rows(raw: NDArray, noise: NoiseModel, offsets: FrequencyOffsets) -> Fused:
    """The fused depths of raw rows (n, 2F) of unwrapped depths [m] and amplitudes [V^2] (:meth:`NoiseModel.fuse`),
    ``offsets`` removed first."""
    with np.errstate(invalid="ignore", divide="ignore", over="ignore"):
        return noise.fuse(raw, offsets_m=offsets.offsets_m, window=offsets.window)
