"""Feature construction and target modes, in one place so training and correction never disagree.

Raw measurements are the per-frequency depths and amplitudes, ordered [depth_f1..depth_fF,
amplitude_f1..amplitude_fF] (the dataset's ``features`` array and a scan's depth/amplitude maps).

Feature sets:
- ``raw``: the paper's 2F inputs as measured.
- ``engineered``: raw, plus what the physics says carries the multipath signature: each depth minus the
  highest-frequency depth, each amplitude over the highest-frequency amplitude, the inverse-variance-weighted
  depth of all frequencies, and the log amplitude of the highest frequency (the signal level, which sets
  the noise).

Target modes:
- ``absolute``: the true depth d_AS (the paper's target).
- ``residual``: the true depth minus the measured highest-frequency depth; the prediction is a correction.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import dask.array as da
import numpy as np
from numpy.typing import NDArray

from mpi_lidar.errors import MpiLidarError

FeatureSet = Literal["raw", "engineered"]
TargetMode = Literal["absolute", "residual"]
FEATURE_SETS: tuple[str, ...] = ("raw", "engineered")
# Engineered features with the residual target: 6.01 mm test MAE at Table I noise against 6.43 mm for the
# paper's raw inputs and absolute target (200,000 train rows; docs/tradeoff.md).
DEFAULT_FEATURE_SET: FeatureSet = "engineered"
DEFAULT_TARGET_MODE: TargetMode = "residual"
TARGET_MODES: tuple[str, ...] = ("absolute", "residual")
# Amplitudes below this are treated as no return when forming ratios and logs. [V^2]
AMPLITUDE_FLOOR_V2 = 1e-12


def frequency_labels(frequencies_hz: tuple[float, ...]) -> list[str]:
    return [f"{f / 1e6:g}MHz" for f in frequencies_hz]


def raw_feature_names(frequencies_hz: tuple[float, ...]) -> list[str]:
    """depth_<f>MHz then amplitude_<f>MHz, in frequency order (the dataset's ``features`` columns)."""
    labels = frequency_labels(frequencies_hz)
    return [f"depth_{x}" for x in labels] + [f"amplitude_{x}" for x in labels]


def weighted_depth(raw: NDArray, frequencies_hz: tuple[float, ...]) -> NDArray[np.float64]:
    """Single-path multi-frequency depth: each depth weighted by its inverse noise variance. [m]

    The phase noise of a frequency scales as sigma / Gamma_f and its depth noise as that over f, so the
    weight is (f Gamma_f)^2 (the per-bin noise sigma is common to all frequencies).
    """
    n_freq = len(frequencies_hz)
    depth = np.asarray(raw[:, :n_freq], dtype=np.float64)
    amplitude = np.asarray(raw[:, n_freq:], dtype=np.float64)
    weights = (np.asarray(frequencies_hz)[None, :] * amplitude) ** 2
    total = weights.sum(1)
    safe = np.where(total > 0, total, 1.0)
    return np.where(total > 0, (weights * depth).sum(1) / safe, depth[:, -1])


@dataclass(frozen=True)
class FeatureSpec:
    """How raw measurements become model inputs and how a prediction becomes a depth."""

    frequencies_hz: tuple[float, ...]
    feature_set: FeatureSet = "raw"
    target_mode: TargetMode = "absolute"

    def __post_init__(self) -> None:
        if self.feature_set not in FEATURE_SETS:
            raise MpiLidarError(f"unknown feature set {self.feature_set!r}; choose one of {', '.join(FEATURE_SETS)}")
        if self.target_mode not in TARGET_MODES:
            raise MpiLidarError(f"unknown target mode {self.target_mode!r}; choose one of {', '.join(TARGET_MODES)}")

    @property
    def n_freq(self) -> int:
        return len(self.frequencies_hz)

    @property
    def raw_names(self) -> list[str]:
        return raw_feature_names(self.frequencies_hz)

    @property
    def names(self) -> list[str]:
        names = self.raw_names
        if self.feature_set == "engineered":
            labels = frequency_labels(self.frequencies_hz)
            top = labels[-1]
            names += [f"depth_{x}_minus_{top}" for x in labels[:-1]]
            names += [f"amplitude_{x}_over_{top}" for x in labels[:-1]]
            names += ["weighted_depth", f"log_amplitude_{top}"]
        return names

    @property
    def residual_reference(self) -> str | None:
        """The measured depth column the residual target is relative to."""
        return self.raw_names[self.n_freq - 1] if self.target_mode == "residual" else None

    def transform(self, raw: NDArray | da.Array) -> NDArray[np.float32] | da.Array:
        """Model inputs from raw measurements (n, 2F), numpy or dask (block by block)."""
        if isinstance(raw, da.Array):
            raw = raw.rechunk({1: -1})
            return raw.map_blocks(self._transform_block, dtype=np.float32, chunks=(raw.chunks[0], (len(self.names),)))
        return self._transform_block(raw)

    def _transform_block(self, raw: NDArray) -> NDArray[np.float32]:
        raw = np.asarray(raw)
        if raw.ndim != 2 or raw.shape[1] != 2 * self.n_freq:
            raise MpiLidarError(f"expected raw measurements of shape (n, {2 * self.n_freq}), got {raw.shape}")
        if self.feature_set == "raw":
            return raw.astype(np.float32, copy=False)
        f = self.n_freq
        depth = raw[:, :f].astype(np.float64)
        amplitude = np.maximum(raw[:, f:].astype(np.float64), AMPLITUDE_FLOOR_V2)
        extra = [
            depth[:, :-1] - depth[:, -1:],
            amplitude[:, :-1] / amplitude[:, -1:],
            weighted_depth(raw, self.frequencies_hz)[:, None],
            np.log(amplitude[:, -1:]),
        ]
        return np.concatenate([raw.astype(np.float64), *extra], axis=1).astype(np.float32)

    def reference_depth(self, raw: NDArray | da.Array) -> NDArray | da.Array:
        """The measured depth a residual is relative to (zero for the absolute target). [m]"""
        if self.target_mode == "absolute":
            return raw[:, 0] * 0.0
        return raw[:, self.n_freq - 1].astype(np.float64)

    def target(self, raw: NDArray | da.Array, true_depth: NDArray | da.Array) -> NDArray | da.Array:
        """What the model learns: the true depth, or the true depth minus the reference depth. [m]"""
        return true_depth - self.reference_depth(raw)

    def depth(self, raw: NDArray | da.Array, prediction: NDArray | da.Array) -> NDArray | da.Array:
        """Corrected depth from a prediction. [m]"""
        return self.reference_depth(raw) + prediction
