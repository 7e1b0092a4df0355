"""What correcting one scan gives (:class:`Correction`): every stage's result that the outputs and reports read."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from mpi_lidar.correction.baseline import FrequencyOffsets
from mpi_lidar.correction.footprint import FootprintEstimate
from mpi_lidar.correction.mixed import SecondReturns
from mpi_lidar.correction.options import MODEL_FLAGS, Estimate, Flag
from mpi_lidar.correction.outcome import Unserved
from mpi_lidar.correction.sensor_reading import SensorReading


@dataclass(frozen=True, kw_only=True)
class Correction:
    """A corrected scan: one depth per pixel, what was done to it, how sure it is, and what each stage found.

    Maps are (H, W); depths in metres. The report's sentences are made from these fields by
    :func:`mpi_lidar.reporting.correction_notes.correction_notes`.

    Attributes
    ----------
    depth : The output depth, NaN where a pixel has none (an invalid pixel). [m]
    flags : What was done to each pixel (:class:`~mpi_lidar.correction.options.Flag`).
    inference_s : Wall seconds of the model's inputs and prediction. [s]
    total_s : Wall seconds of the whole correction. [s]
    gate_s : Wall seconds of the scene geometry and the gate. [s]
    multipath_bias_m : The scene geometry's expected multipath bias (None: not analysed, or no geometry). [m]
    cpu_s : CPU seconds of this process (every thread) per stage: validity, gate, inference. [s]
    calibration : The scan's own footprint estimate, where the footprint was "auto" and the geometry analysed.
    unserved : Why the model could not serve the scan (None: it could).
    measured_depth : The highest frequency's depth as measured, unwrapped into one range where the scan's depths
        were wrapped (as measured where the range is ambiguous): what correction compares with. [m]
    unwrap_confidence : The unwrapping's confidence (None: the scan's depths came unwrapped). [1]
    estimate : Which estimate each depth is (:class:`~mpi_lidar.correction.options.Estimate`).
    uncertainty_m : Each depth's 1-sigma uncertainty (NaN where it has none). [m]
    amplitude_units_per_v2 : The scanner's amplitude unit per V^2 the amplitudes were divided by (1: V^2); outputs
        that show amplitudes in V^2 divide by it too. [1 / V^2]
    reading : What the scan said of its sensor: its noise law, the unit and whether its evidence contradicts V^2
        (None: not read).
    offsets : What the fused depths removed from each frequency (:class:`FrequencyOffsets`).
    scene_notes : What the scene geometry says of the scan in words (no geometry, and the like).
    uncalibrated_pixels : Pixels that could hold multipath above the gate's threshold but were left alone because
        the scan's own footprint estimate is not significant.
    beyond_prior_pixels : Corrected pixels whose geometric inputs lie beyond the model's training prior.
    prior_reach : The largest rho_ABA [1] and d_AB [m] of that prior (None: not known).
    second_returns : The weaker return of each pixel resolved into two (flag two_returns; None: none was).
    """

    depth: NDArray[np.float32]
    flags: NDArray[np.uint8]
    inference_s: float = 0.0
    total_s: float = 0.0
    gate_s: float = 0.0
    multipath_bias_m: NDArray[np.float32] | None = None
    cpu_s: dict[str, float] = field(default_factory=dict)
    calibration: FootprintEstimate | None = None
    unserved: Unserved | None = None
    measured_depth: NDArray[np.float32] | None = None
    unwrap_confidence: NDArray[np.float32] | None = None
    estimate: NDArray[np.uint8] | None = None
    uncertainty_m: NDArray[np.float32] | None = None
    amplitude_units_per_v2: float = 1.0
    reading: SensorReading | None = None
    offsets: FrequencyOffsets = field(default_factory=FrequencyOffsets)
    scene_notes: tuple[str, ...] = ()
    uncalibrated_pixels: int = 0
    beyond_prior_pixels: int = 0
    prior_reach: tuple[float, float] | None = None
    second_returns: SecondReturns | None = None

    @property
    def frequency_offsets_m(self) -> tuple[float, ...] | None:
        """The frequencies' depth offsets relative to the highest that the fused depths removed (None: none). [m]"""
        return None if self.offsets.offsets_m is None else tuple(float(o) for o in self.offsets.offsets_m)

    @property
    def window_leakage_removed(self) -> bool:
        """Whether the fused depths had the integration window's leakage removed before the offsets."""
        return self.offsets.window

    def counts(self) -> dict[str, int]:
        """Pixels per flag (:class:`~mpi_lidar.correction.options.Flag`), by lower-case name."""
        found = code_counts(self.flags, len(Flag))
        return {flag.name.lower(): int(found[int(flag)]) for flag in Flag}

    def model_pixels(self) -> int:
        """Pixels whose depth is the model's, inside the training prior and beyond it (``MODEL_FLAGS``)."""
        return int(np.isin(self.flags, MODEL_FLAGS).sum())

    def estimate_counts(self) -> dict[str, int]:
        """Pixels per estimate (:class:`~mpi_lidar.correction.options.Estimate`): none, measured, fused, corrected."""
        if self.estimate is None:
            return {}
        found = code_counts(self.estimate, len(Estimate))
        return {estimate.name.lower(): int(found[int(estimate)]) for estimate in Estimate}

    def uncertainty_summary(self) -> dict[str, float]:
        """Median and 95th percentile of the depths' 1-sigma uncertainty [m] over the pixels that have one."""
        if self.uncertainty_m is None or not np.isfinite(self.uncertainty_m).any():
            return {}
        median, high = np.nanpercentile(self.uncertainty_m, [50, 95])
        return {"median_m": float(median), "p95_m": float(high)}


# Codes counted at a time (:func:`code_counts`): np.bincount widens its input to intp first, eight bytes a pixel.
COUNT_CHUNK_PIXELS = 2**20


def code_counts(codes: NDArray[np.uint8], length: int) -> NDArray[np.intp]:
    """How many of ``codes`` (any shape) take each value below ``length`` (length,), a chunk of
    ``COUNT_CHUNK_PIXELS`` at a time, so that a whole scan is never widened to intp at once."""
    flat = codes.reshape(-1)
    found = np.zeros(length, dtype=np.intp)
    for start in range(0, flat.size, COUNT_CHUNK_PIXELS):
        found += np.bincount(flat[start:start + COUNT_CHUNK_PIXELS], minlength=length)[:length]
    return found
