"""The model stage: the corrected depth of the pixels the gate hands the model, from their raw measurements and,
for a geometric model, the scene geometry's inputs (:func:`predict_rows`)."""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from mpi_lidar.correction.footprint import PlaneModelInputs
from mpi_lidar.correction.gating import in_depth_range
from mpi_lidar.correction.options import CorrectionOptions
from mpi_lidar.correction.tiles import PARALLEL_MIN_ROWS
from mpi_lidar.learning.error_model import beyond_prior
from mpi_lidar.learning.features import geometry_inputs
from mpi_lidar.learning.model import CorrectionModel
from mpi_lidar.threads import on_cores_by_rows

# Pixels whose geometric inputs are worked out at once: the sums over their partners' patches take about a
# kilobyte a pixel while they are made.
GEOMETRY_INPUT_PIXELS = 16_384


def in_model_range(depth: NDArray, model: CorrectionModel, options: CorrectionOptions) -> NDArray[np.bool_]:
    """Whether measured depths [m] lie in the d_AS range of the model's training prior (plus a tolerance,
    :func:`~mpi_lidar.correction.gating.in_depth_range`)."""
    return in_depth_range(depth, model.card.dataset.prior.d_as_m, options)


@dataclass(frozen=True)
class RowsPredicted:
    """The model's output for some rows (:func:`predict_rows`).

    depth_m : Corrected depth per row (n,). [m]
    inputs_cpu_s : CPU seconds the geometric inputs took (the gate's share). [s]
    inputs_wall_s : The longest wall seconds a thread spent on them. [s]
    beyond_prior : Rows whose geometric inputs lie beyond the training prior's reach.
    inputs : A geometric model's inputs per row (n, 2), equivalent rho_ABA [1] and d_AB [m] (None for a model
        without them, or where the scan gave none): where in the prior each row lies, for its uncertainty.
    """

    depth_m: NDArray[np.float64]
    inputs_cpu_s: float
    inputs_wall_s: float
    beyond_prior: int
    inputs: NDArray[np.float64] | None = None


def predict_rows(model: CorrectionModel, raw: NDArray, pixels: NDArray, inputs: PlaneModelInputs | None,
                 reach: tuple[float, float] | None = None) -> RowsPredicted:
    """Corrected depth of raw rows (n, 2F) [m, V^2] of flat pixel indices ``pixels`` (n,).

    The model's inputs, with the geometric ones of ``inputs`` where the model takes them, are built in row ranges
    on the cores into one array; the model then predicts them all at once. ``reach`` is the largest rho_ABA [1] and
    d_AB [m] of the training prior (:meth:`~mpi_lidar.learning.model_card.PriorCard.multipath_reach`); None: rows beyond
    it are not counted.
    """
    features = np.empty((raw.shape[0], len(model.spec.names)), dtype=np.float32)
    top = raw.shape[1] // 2 - 1  # the highest frequency's depth column
    read = np.empty((raw.shape[0], 2)) if inputs is not None and model.geometric else None

    def build(rows: slice) -> tuple[float, float, int]:
        cpu, wall = time.thread_time(), time.perf_counter()
        geometric, beyond = None, 0
        if read is not None and inputs is not None:
            geometric = read[rows] = _geometric_inputs(inputs, pixels[rows], raw[rows, top])
            if reach is not None:
                beyond = int(beyond_prior(geometric, reach).sum())
        gate_share = (time.thread_time() - cpu, time.perf_counter() - wall)
        model.spec.transform_into(raw[rows], geometric, features[rows])
        return (*gate_share, beyond)

    shares = on_cores_by_rows(build, raw.shape[0], PARALLEL_MIN_ROWS)
    return RowsPredicted(model.depth_from_features(raw, features), sum(cpu for cpu, _, _ in shares),
                         max(wall for _, wall, _ in shares), sum(count for _, _, count in shares), read)


def _geometric_inputs(inputs: PlaneModelInputs, pixels: NDArray, measured_range: NDArray) -> NDArray[np.float64]:
    """A geometric model's inputs (n, 2) of flat pixel indices ``pixels`` (n,) whose highest-frequency range is
    ``measured_range`` (n,) [m] (:meth:`PlaneModelInputs.pixels`), ``GEOMETRY_INPUT_PIXELS`` at a time."""
    starts = range(0, max(pixels.size, 1), GEOMETRY_INPUT_PIXELS)  # no pixels: one call, for the (0, 2) shape
    return np.concatenate([geometry_inputs(*inputs.pixels(
        pixels[start:start + GEOMETRY_INPUT_PIXELS],
        measured_range[start:start + GEOMETRY_INPUT_PIXELS].astype(np.float64))) for start in starts])
