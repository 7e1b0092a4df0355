"""Calibration of a sensor from its own scans: what ``mpi-lidar calibrate`` measures and the profile it writes.

- :mod:`~mpi_lidar.calibration.flat_residuals`: each frequency's depth less its block's plane on a scan's flat
  surfaces, away from multipath and edges (:func:`flat_surface_residuals`).
- :mod:`~mpi_lidar.calibration.sensor_scale`: the amplitude unit, noise scale and frequency offsets those
  residuals say (:func:`estimate_sensor_scale`; :func:`measure_sensor_scale` from a scan).
- :mod:`~mpi_lidar.calibration.profile`: the sensor profile (``sensor.toml``) that holds them with the footprint,
  and the correction options it sets (:func:`read_profile`, :func:`write_profile`, :func:`profile_options`).

Each name of ``__all__`` is imported from its module on first access (PEP 562), so reading a profile does not
import the estimator's scene geometry and optimizer.
"""

from __future__ import annotations

from importlib import import_module
from typing import TYPE_CHECKING

if TYPE_CHECKING:  # the names for type checkers; at run time __getattr__ imports them
    from mpi_lidar.calibration.flat_residuals import FlatSurfaceResiduals, flat_surface_residuals
    from mpi_lidar.calibration.profile import SensorProfile, profile_options, read_profile, write_profile
    from mpi_lidar.calibration.sensor_scale import SensorScale, estimate_sensor_scale, measure_sensor_scale

_MODULES = {
    "mpi_lidar.calibration.flat_residuals": ("FlatSurfaceResiduals", "flat_surface_residuals"),
    "mpi_lidar.calibration.profile": ("SensorProfile", "profile_options", "read_profile", "write_profile"),
    "mpi_lidar.calibration.sensor_scale": ("SensorScale", "estimate_sensor_scale", "measure_sensor_scale"),
}
_EXPORTS = {name: module for module, names in _MODULES.items() for name in names}

__all__ = [
    "FlatSurfaceResiduals", "SensorProfile", "SensorScale", "estimate_sensor_scale", "flat_surface_residuals",
    "measure_sensor_scale", "profile_options", "read_profile", "write_profile",
]


def __getattr__(name: str) -> object:
    module = _EXPORTS.get(name)
    if module is None:
        raise AttributeError(f"module 'mpi_lidar.calibration' has no attribute {name!r}")
    value = getattr(import_module(module), name)
    globals()[name] = value  # the next access does not come here
    return value


def __dir__() -> list[str]:
    return sorted({*globals(), *__all__})
