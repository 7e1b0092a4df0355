"""Batch correction of scans: validity mask, a gate that skips pixels needing no correction, inference.

Each pixel gets one flag saying what was done (:class:`Flag`). Invalid pixels (no finite value, no return
above the noise floor, saturated, frequencies that disagree by more than a phase wrap could explain) keep
NaN. Valid pixels whose depth lies outside the range the model was trained on keep their raw depth (trees
do not extrapolate). Valid pixels the gate lets through are corrected by the model; the others keep the
raw depth of the highest frequency, exactly as measured. The default gate, ``geometry``, corrects only
where the scan's own geometry lets another surface send light back (:mod:`mpi_lidar.scans.geometry`); a scan
without geometry falls back to pixel-wise correction of every valid pixel, and its report says so. A model
trained with geometric inputs gets the geometry's coupling and d_AB for each pixel it corrects (computed
even under another gate); on a scan without geometry it corrects nothing, and the report says so.

Per scan the outputs go into ``<out>/<scan name>/`` (``corrected.zarr``, report files, point clouds),
built in a temporary directory and renamed into place, so a scan's outputs are all there or not at all. A
scan already corrected by the same model with the same options (same content hashes) is skipped.
"""
from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from mpi_lidar.config import SensorConfig
from mpi_lidar.correction.gates import NO_GEOMETRY_INPUTS_NOTE, NO_GEOMETRY_NOTE, geometry_gate, make_gate
from mpi_lidar.correction.options import INVALID_FLAGS, CorrectionOptions, Flag
from mpi_lidar.correction.validity import validity_flags
from mpi_lidar.learning.features import geometry_inputs
from mpi_lidar.learning.model import CorrectionModel
from mpi_lidar.scans.scan import Scan


@dataclass(frozen=True)
class Correction:
    """A corrected scan: depth (H, W) [m] (NaN where invalid), flags (H, W), and what it cost.

    ``multipath_bias_m`` (H, W) is the geometry gate's expected multipath bias [m] (None for other gates
    or without geometry); ``gate_s`` the time the gate took [s]; ``notes`` what the report must say.
    """

    depth: NDArray[np.float32]
    flags: NDArray[np.uint8]
    inference_s: float
    total_s: float
    gate_s: float = 0.0
    multipath_bias_m: NDArray[np.float32] | None = None
    notes: tuple[str, ...] = ()

    def counts(self) -> dict[str, int]:
        values, counts = np.unique(self.flags, return_counts=True)
        found = dict(zip(values.tolist(), counts.tolist(), strict=True))
        return {flag.name.lower(): int(found.get(int(flag), 0)) for flag in Flag}


def in_model_range(depth: NDArray, model: CorrectionModel, options: CorrectionOptions) -> NDArray[np.bool_]:
    """Whether measured depths [m] lie in the d_AS range of the model's training prior (plus a tolerance)."""
    return in_depth_range(depth, model.card.dataset.prior.d_as_m, options)


def in_depth_range(depth: NDArray, d_as_m: tuple[float, float], options: CorrectionOptions) -> NDArray[np.bool_]:
    """Whether measured depths [m] lie in the range ``d_as_m`` [m] widened by ``options.range_tolerance_m``."""
    low, high = d_as_m
    return (depth >= low - options.range_tolerance_m) & (depth <= high + options.range_tolerance_m)


def correct_scan(scan: Scan, model: CorrectionModel, options: CorrectionOptions,
                 sensor: SensorConfig | None = None) -> Correction:
    """Correct one scan in this process, pixel by pixel, in tiles of ``options.tile_pixels``."""
    started = time.perf_counter()
    model.check_compatible(scan.frequencies_hz, model.spec.raw_names, f"scan {scan.name}")
    sensor = sensor or SensorConfig()
    raw = scan.raw_pixels()
    flags = validity_flags(raw, scan.frequencies_hz, options, sensor)
    flags[(flags == Flag.NOT_NEEDED) & ~in_model_range(raw[:, len(scan.frequencies_hz) - 1], model, options)] = (
        Flag.OUT_OF_RANGE)
    gate_started = time.perf_counter()
    gate = make_gate(options)
    top = raw[:, len(scan.frequencies_hz) - 1]
    usable = ~np.isin(flags, [int(f) for f in INVALID_FLAGS])
    usable_depth = np.where(usable, top, np.nan)
    candidates = gate.scan_candidates(scan, usable_depth)
    notes: tuple[str, ...] = ()
    potential = getattr(gate, "potential_", None)
    if model.geometric and potential is None:
        potential = geometry_gate(options).potential(scan, usable_depth)
    if candidates is not None:
        flags[(flags == Flag.NOT_NEEDED) & ~candidates] = Flag.NO_MULTIPATH
    elif gate.uses_geometry and not model.geometric:
        notes = (NO_GEOMETRY_NOTE,)
    valid = np.flatnonzero(flags == Flag.NOT_NEEDED)
    needs = valid[gate.needs_correction(raw[valid], scan.frequencies_hz, sensor)]
    if model.geometric and potential is None:
        needs, notes = needs[:0], (NO_GEOMETRY_INPUTS_NOTE,)
    geometric_inputs = None if potential is None else geometry_inputs(potential.coupling, potential.d_ab_m)
    gate_s = time.perf_counter() - gate_started
    depth = usable_depth.copy()
    inference_started = time.perf_counter()
    for start in range(0, needs.size, options.tile_pixels):
        tile = needs[start:start + options.tile_pixels]
        depth[tile] = model.predict_depth(raw[tile], None if geometric_inputs is None else geometric_inputs[tile])
    inference_s = time.perf_counter() - inference_started
    flags[needs] = Flag.CORRECTED
    h, w = scan.shape
    return Correction(depth.reshape(h, w).astype(np.float32), flags.reshape(h, w), inference_s,
                      time.perf_counter() - started, gate_s,
                      None if potential is None else potential.bias_m.astype(np.float32), notes)
