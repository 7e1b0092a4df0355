"""Correction of one scan: validity mask, gates that skip what needs no correction, inference per pixel."""

from __future__ import annotations

from mpi_lidar.correction.correct import Correction, correct_scan, in_model_range
from mpi_lidar.correction.gates import (
    NO_GEOMETRY_INPUTS_NOTE,
    NO_GEOMETRY_NOTE,
    ConsistencyGate,
    CorrectAll,
    Gate,
    GeometryGate,
    geometry_gate,
    make_gate,
)
from mpi_lidar.correction.options import (
    CORRECTED_SCHEMA,
    GATES,
    INVALID_FLAGS,
    CorrectionOptions,
    Flag,
    ScanStatus,
)
from mpi_lidar.correction.outcome import ScanOutcome
from mpi_lidar.correction.validity import noise_floor_v2, quadrature_noise_v2, validity_flags

__all__ = [
    "CORRECTED_SCHEMA", "GATES", "INVALID_FLAGS", "NO_GEOMETRY_INPUTS_NOTE", "NO_GEOMETRY_NOTE", "ConsistencyGate",
    "CorrectAll", "Correction", "CorrectionOptions", "Flag", "Gate", "GeometryGate", "ScanOutcome", "ScanStatus",
    "correct_scan", "geometry_gate", "in_model_range", "make_gate", "noise_floor_v2", "quadrature_noise_v2",
    "validity_flags",
]
