"""Which pixels can be trusted at all: one range from the wrapped depths, finite, above the noise floor,
unsaturated, frequencies consistent."""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from mpi_lidar.config import SensorConfig
from mpi_lidar.correction.options import INVALID_FLAGS, CorrectionOptions, Flag

# The noise model correction's stages weigh pixels by, re-exported from where the simulator's physics keeps it.
from mpi_lidar.physics.noise import depth_noise_m, noise_floor_v2, quadrature_noise_v2, unwrapped_rows

__all__ = ["UNUSABLE_FLAGS", "depth_noise_m", "depth_rules_only", "noise_floor_v2", "quadrature_noise_v2",
           "unwrapped_rows", "usable_depth_of", "validity_flags"]

def validity_flags(raw: NDArray, frequencies_hz: tuple[float, ...], options: CorrectionOptions,
                   sensor: SensorConfig, confidence: NDArray | None = None) -> NDArray[np.uint8]:
    """Flag per pixel: NOT_NEEDED for valid pixels (the gate decides later), else the first reason it is invalid.

    ``confidence`` (n,): the unwrapping's confidence of rows whose depths were unwrapped (:func:`unwrapped_rows`);
    rows below ``options.min_unwrap_confidence`` are AMBIGUOUS, unless a more basic reason holds.
    """
    f = len(frequencies_hz)
    depth, amplitude = raw[:, :f], raw[:, f:]
    flags = np.full(raw.shape[0], Flag.NOT_NEEDED, dtype=np.uint8)
    high = low = depth[:, 0]
    for column in range(1, f):  # column by column: a row reduction over F values is several times slower
        high, low = np.maximum(high, depth[:, column]), np.minimum(low, depth[:, column])
    spread = high - low  # NaN where a depth is NaN, as a row's max - min: those rows are NOT_FINITE
    floor = options.min_amplitude_sigmas * noise_floor_v2(sensor, tuple(frequencies_hz))
    ambiguous = np.zeros(raw.shape[0], bool) if confidence is None else ~(confidence >= options.min_unwrap_confidence)
    rules = [
        (Flag.INCONSISTENT, spread > options.max_depth_spread_m),
        (Flag.AMBIGUOUS, ambiguous),
        (Flag.SATURATED, (amplitude > options.saturation_amplitude_v2).any(axis=1)),
        (Flag.NO_RETURN, (amplitude < floor[None, :]).any(axis=1)),
        (Flag.NOT_FINITE, ~np.isfinite(raw).all(axis=1)),
    ]
    for flag, where in rules:  # later rules win: the most basic reason is reported
        flags[where] = flag
    return flags



# Pixels whose depth the scene geometry and the model cannot use: the invalid ones, and those of an unknown range.
UNUSABLE_FLAGS = (*INVALID_FLAGS, Flag.AMBIGUOUS)


def usable_depth_of(raw: NDArray, flags: NDArray) -> NDArray:
    """The highest-frequency depth (n,) [m] of raw rows (n, 2F) whose ``flags`` (n,) are not invalid
    (:data:`INVALID_FLAGS`) or ambiguous, NaN elsewhere: what the scene geometry is worked out from."""
    f = raw.shape[1] // 2
    return np.where(~np.isin(flags, [int(flag) for flag in UNUSABLE_FLAGS]), raw[:, f - 1], np.nan)


def depth_rules_only(options: CorrectionOptions) -> CorrectionOptions:
    """``options`` without amplitude thresholds (no-return floor 0, saturation out of reach): validity from the
    depths alone, for amplitudes whose unit is not known yet."""
    return options.model_copy(update={"min_amplitude_sigmas": 0.0, "saturation_amplitude_v2": 1e30})
