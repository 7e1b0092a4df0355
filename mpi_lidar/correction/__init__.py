"""Correction of one scan: validity mask -> scene geometry -> gates that skip what needs no correction -> model.

Each name of ``__all__`` is imported from its module on first access (PEP 562), so the options, flags and
statuses (``from mpi_lidar.correction import CorrectionOptions``) come without the model's libraries
(XGBoost, Dask) that :func:`correct_scan` needs.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from mpi_lidar.lazy import lazy_exports

if TYPE_CHECKING:  # the names for type checkers; at run time __getattr__ imports them
    from mpi_lidar.correction.correct import Correction, correct_scan, in_model_range
    from mpi_lidar.correction.gates import ConsistencyGate, CorrectAll, Gate, GeometryGate, make_gate
    from mpi_lidar.correction.options import (
        CORRECTED_SCHEMA,
        GATES,
        INVALID_FLAGS,
        MODEL_FLAGS,
        CorrectionOptions,
        Flag,
        GateName,
        ScanStatus,
        UnservedReason,
    )
    from mpi_lidar.correction.outcome import ScanOutcome, Unserved
    from mpi_lidar.correction.scene import NO_GEOMETRY_INPUTS_NOTE, NO_GEOMETRY_NOTE, SceneGeometry, analyse_geometry
    from mpi_lidar.correction.validity import validity_flags
    from mpi_lidar.physics.noise import NoiseModel, depth_noise_m, noise_floor_v2, quadrature_noise_v2

_MODULES = {
    "mpi_lidar.correction.correct": ("Correction", "correct_scan", "in_model_range"),
    "mpi_lidar.correction.gates": ("ConsistencyGate", "CorrectAll", "Gate", "GeometryGate", "make_gate"),
    "mpi_lidar.correction.options": ("CORRECTED_SCHEMA", "GATES", "INVALID_FLAGS", "MODEL_FLAGS",
                                     "CorrectionOptions", "Flag",
                                     "GateName", "ScanStatus", "UnservedReason"),
    "mpi_lidar.correction.outcome": ("ScanOutcome", "Unserved"),
    "mpi_lidar.correction.scene": ("NO_GEOMETRY_INPUTS_NOTE", "NO_GEOMETRY_NOTE", "SceneGeometry", "analyse_geometry"),
    "mpi_lidar.correction.validity": ("validity_flags",),
    "mpi_lidar.physics.noise": ("NoiseModel", "depth_noise_m", "noise_floor_v2", "quadrature_noise_v2"),
}
_EXPORTS = {name: module for module, names in _MODULES.items() for name in names}

__all__ = [
    "CORRECTED_SCHEMA", "GATES", "INVALID_FLAGS", "MODEL_FLAGS", "NO_GEOMETRY_INPUTS_NOTE",
    "NO_GEOMETRY_NOTE", "ConsistencyGate",
    "CorrectAll", "Correction", "CorrectionOptions", "Flag", "Gate", "GateName", "GeometryGate", "NoiseModel",
    "ScanOutcome",
    "ScanStatus", "SceneGeometry", "Unserved", "UnservedReason", "analyse_geometry", "correct_scan",
    "depth_noise_m", "in_model_range",
    "make_gate", "noise_floor_v2", "quadrature_noise_v2", "validity_flags",
]

__getattr__, __dir__ = lazy_exports(__name__, _EXPORTS, __all__)
