"""The per-pixel estimate: the second and last pass over a scan's tiles, after the scene geometry and the gate.

Each tile's pixels get, in turn, the model's depth where the gate hands them to it (:mod:`.prediction`), the
baseline's elsewhere (:mod:`.baseline`), and their uncertainty (:mod:`.uncertainty`); which estimate each depth
is goes with them (:class:`~mpi_lidar.correction.options.Estimate`).
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from mpi_lidar.correction.baseline import BASELINE_FLAGS, FrequencyOffsets, fuse_rows
from mpi_lidar.correction.footprint import FootprintEstimate, PlaneModelInputs
from mpi_lidar.correction.mixed import SecondReturns
from mpi_lidar.correction.options import INVALID_FLAGS, Baseline, CorrectionOptions, Estimate, Flag
from mpi_lidar.correction.prediction import predict_rows
from mpi_lidar.correction.tiles import PARALLEL_MIN_ROWS, StageClock, raw_tiles
from mpi_lidar.correction.uncertainty import corrected_uncertainty_m, left_alone_sigma_m, measured_sigma_m
from mpi_lidar.correction.validity import Validity
from mpi_lidar.learning.error_model import beyond_prior
from mpi_lidar.learning.model import CorrectionModel
from mpi_lidar.physics.noise import NoiseModel
from mpi_lidar.scans.scan import Scan
from mpi_lidar.threads import on_cores_by_rows


@dataclass(frozen=True)
class PixelEstimates:
    """The per-pixel estimate's result; maps (H*W,).

    depth : The output depth: the model's where CORRECTED, the baseline's for the other valid pixels, the measured
        depth where the range is ambiguous, NaN where invalid. [m]
    estimate : Which estimate each depth is (:class:`Estimate`).
    uncertainty_m : Each depth's 1-sigma (NaN where it has none, and where the range is ambiguous). [m]
    beyond_prior_pixels : Corrected pixels whose geometric inputs lie beyond the training prior.
    inference_s : Wall seconds of the model's inputs and prediction. [s]
    inputs_s : Wall seconds of the geometric inputs (the gate's share of the model's work). [s]
    beyond_prior : Bool (H*W,): the corrected pixels whose geometric inputs lie beyond the training prior (None
        where the model takes none or its card does not say how far its prior reaches).
    """

    depth: NDArray[np.float32]
    estimate: NDArray[np.uint8]
    uncertainty_m: NDArray[np.float32]
    beyond_prior_pixels: int
    inference_s: float
    inputs_s: float
    beyond_prior: NDArray[np.bool_] | None = None


@dataclass(frozen=True)
class ScenePart:
    """What the per-pixel estimate reads of the scene geometry: the geometric model's inputs, the multipath bias
    [m] a depth left alone carries in its uncertainty at flat pixel indices (n,)
    (:meth:`~mpi_lidar.correction.scene.SceneGeometry.left_alone_bias_m`), and the scan's own footprint estimate
    (each None where the scene has none)."""

    inputs: PlaneModelInputs | None = None
    left_alone_bias_m: Callable[[NDArray], NDArray[np.float64]] | None = None
    footprint: FootprintEstimate | None = None


def estimate_pixels(scan: Scan, tiles: list[slice], noise: NoiseModel, flags: NDArray[np.uint8], validity: Validity,
                    scene: ScenePart, model: CorrectionModel, offsets: FrequencyOffsets, options: CorrectionOptions,
                    clock: StageClock, second_returns: SecondReturns | None = None) -> PixelEstimates:
    """Every pixel's depth, estimate and uncertainty (:class:`PixelEstimates`), tile by tile; ``flags`` are the gate
    stage's, ``scan`` the validity stage's (depths in one range, amplitudes in V^2); ``second_returns`` the mixed-
    pixel stage's, whose fit gives the pixels it resolved their uncertainty."""
    depth = validity.usable_depth.copy()
    ambiguous = np.flatnonzero(flags == Flag.AMBIGUOUS)
    depth[ambiguous] = validity.measured_depth[ambiguous]  # a range that cannot be told: as measured
    estimate = np.full(flags.size, Estimate.NONE, dtype=np.uint8)
    uncertainty = np.full(flags.size, np.nan, dtype=np.float32)
    reach = model.card.dataset.prior.multipath_reach()
    fuse = Baseline(options.baseline) == Baseline.FUSED
    # A pixel resolved into two returns keeps the stronger one's depth, with its own sd from the two-return fit (its
    # Cramer-Rao bound, or the measured sd widened by the frequencies' disagreement where it is not known; then, as
    # every depth left alone, the multipath bias the scene expects): never fused, never without an uncertainty.
    resolved_sigma = (None if second_returns is None or second_returns.stronger_sigma_m is None
                      else second_returns.stronger_sigma_m.reshape(-1))
    known = [int(flag) for flag in (*BASELINE_FLAGS, Flag.CORRECTED, Flag.TWO_RETURNS)]
    invalid = [int(flag) for flag in INVALID_FLAGS]
    beyond, inference_s, inputs_s = 0, 0.0, 0.0
    reads_inputs = model.geometric and scene.inputs is not None
    past = np.zeros(flags.size, dtype=bool) if reads_inputs and reach is not None else None
    for pixels, raw in raw_tiles(scan, tiles):
        cpu, started = time.process_time(), time.perf_counter()
        # The geometric inputs each corrected pixel's model read: where in the prior it lies, for its uncertainty.
        # A tile's only (float64, 16 bytes a pixel): the whole scan's would be the stage's largest array.
        read = np.full((raw.shape[0], 2), np.nan) if reads_inputs else None
        needs = np.flatnonzero(flags[pixels] == Flag.CORRECTED)
        if needs.size:
            predicted = predict_rows(model, raw[needs], pixels.start + needs, scene.inputs, reach)
            depth[pixels.start + needs] = predicted.depth_m
            if read is not None and predicted.inputs is not None:
                read[needs] = predicted.inputs
            beyond += predicted.beyond_prior
            inputs_s += predicted.inputs_wall_s
            clock.add("gate", predicted.inputs_cpu_s)
            clock.add("inference", time.process_time() - cpu - predicted.inputs_cpu_s)
            inference_s += time.perf_counter() - started - predicted.inputs_wall_s
        cpu = time.process_time()

        def estimate_rows(rows: slice, start: int = pixels.start, raw: NDArray = raw,
                          read: NDArray | None = read) -> None:
            where = slice(start + rows.start, start + rows.stop)
            tile_flags = flags[where]
            estimate[where] = np.where(np.isin(tile_flags, invalid), Estimate.NONE, Estimate.MEASURED)
            present = np.flatnonzero(np.isin(tile_flags, known))
            fused = fuse_rows(raw[rows][present], noise, offsets)
            measured_sigma = measured_sigma_m(fused)
            index = where.start + present
            corrected = tile_flags[present] == Flag.CORRECTED
            expected = (np.zeros(present.size) if scene.left_alone_bias_m is None
                        else scene.left_alone_bias_m(index))
            sigma = np.array(measured_sigma)
            resolved = tile_flags[present] == Flag.TWO_RETURNS
            if resolved_sigma is not None and resolved.any():
                bound = resolved_sigma[index[resolved]]
                sigma[resolved] = np.where(np.isfinite(bound), bound, measured_sigma[resolved])
            if fuse:
                take = ~corrected & fused.consistent & ~resolved
                depth[index[take]] = fused.depth_m[take]
                sigma[take] = fused.sigma_m[take]
                estimate[index[take]] = Estimate.FUSED
            uncertainty[index] = left_alone_sigma_m(sigma, expected)
            uncertainty[index[corrected]] = corrected_uncertainty_m(
                model.card, measured_sigma[corrected], fused.sigma_m[corrected],
                depth[index[corrected]] - validity.measured_depth[index[corrected]], scene.footprint,
                None if read is None else read[index[corrected] - start])
            estimate[index[corrected]] = Estimate.CORRECTED

        on_cores_by_rows(estimate_rows, raw.shape[0], PARALLEL_MIN_ROWS)
        clock.add("baseline", time.process_time() - cpu)
        if past is not None and read is not None and reach is not None:
            past[pixels] = beyond_prior(np.nan_to_num(read, nan=0.0), reach) & (flags[pixels] == Flag.CORRECTED)
    return PixelEstimates(depth, estimate, uncertainty, beyond, inference_s, inputs_s, past)

