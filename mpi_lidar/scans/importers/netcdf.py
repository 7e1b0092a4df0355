"""NetCDF (3 or 4) and HDF5 files, read through xarray."""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import TYPE_CHECKING, ClassVar

import numpy as np
from numpy.typing import NDArray

from mpi_lidar.scans.importers.base import (
    ScanImporter,
    check_regular_file,
    check_variables,
    import_arrays,
    select_variables,
    speed_of_light_of,
    stored_frequencies,
)
from mpi_lidar.scans.scan import Scan, ScanError
from mpi_lidar.scans.store import check_memory_budget

if TYPE_CHECKING:
    import xarray as xr

# Units a NetCDF/HDF5 variable may declare (its ``units`` attribute), as factors to the store's unit; a
# variable without ``units`` is taken to be in the store's unit already.
_METRES = {"m": 1.0, "meter": 1.0, "meters": 1.0, "metre": 1.0, "metres": 1.0, "cm": 1e-2, "mm": 1e-3, "km": 1e3}
_RADIANS = {"rad": 1.0, "radian": 1.0, "radians": 1.0, "deg": np.pi / 180, "degree": np.pi / 180,
            "degrees": np.pi / 180}
_HERTZ = {"hz": 1.0, "khz": 1e3, "mhz": 1e6, "ghz": 1e9}
_METRES_PER_SECOND = {"m/s": 1.0, "m s-1": 1.0, "m.s-1": 1.0, "m s^-1": 1.0, "km/s": 1e3, "km s-1": 1e3}
UNITS = {"depth": ("m", _METRES), "reference_depth": ("m", _METRES), "azimuth_rad": ("rad", _RADIANS),
         "elevation_rad": ("rad", _RADIANS), "frequencies_hz": ("Hz", _HERTZ), "wrap_period_m": ("m", _METRES),
         "speed_of_light_m_per_s": ("m/s", _METRES_PER_SECOND)}
_HDF5_MAGIC = b"\x89HDF\r\n\x1a\n"
_NETCDF3_MAGIC = b"CDF"


class NetcdfImporter(ScanImporter):
    """NetCDF and HDF5 files (:func:`load_netcdf`)."""

    suffixes: ClassVar[tuple[str, ...]] = (".nc", ".h5", ".hdf5")

    def load(self, path: Path, frequencies_hz: tuple[float, ...] | None = None,
             variables: Mapping[str, str] | None = None, speed_of_light_m_per_s: float | None = None) -> Scan:
        return load_netcdf(path, frequencies_hz, variables, speed_of_light_m_per_s)


def load_netcdf(path: str | Path, frequencies_hz: tuple[float, ...] | None = None,
                variables: Mapping[str, str] | None = None, speed_of_light_m_per_s: float | None = None) -> Scan:
    """Import a NetCDF (3 or 4) or HDF5 file through xarray: its variables named as in the scan store (or an
    alias: ``azimuth``, ``elevation``, ``azimuth_deg``, ``elevation_deg``, ``frequency_hz``), or mapped by
    ``variables`` (``{"depth": "range_m", "amplitude": "intensity", "azimuth_deg": "az"}``).

    Every variable is accounted for (:func:`~mpi_lidar.scans.importers.base.select_variables`): a variable that
    is neither a scan array, nor left out with ``{"ignore": "a,b"}``, nor metadata (a dimension coordinate, a
    variable named like its only dimension, or a scalar) is refused. The frequencies come from
    ``frequencies_hz``, else the variable ``frequencies_hz`` (or ``frequency_hz``), else the global attribute
    ``frequencies_hz``; either way they are checked to be Hz (not MHz). CF decoding applies (``_FillValue``
    becomes NaN, ``scale_factor``), and a ``units`` attribute is converted (mm, cm or km to m, degrees to rad,
    kHz, MHz or GHz to Hz; other units are refused); a ``_deg`` name without ``units`` holds degrees. Each
    variable's dtype and declared size are checked against the memory budget before anything is read. The speed
    of light the depths were converted with [m/s] is the variable or global attribute ``speed_of_light_m_per_s``,
    or that of ``wrap_period_m`` (each frequency's c / 2f [m], a variable or attribute), or
    ``speed_of_light_m_per_s`` given, else 299,792,458 m/s (:func:`~mpi_lidar.scans.importers.base.speed_of_light_of`).
    """
    import xarray as xr

    path = Path(path)
    check_variables(variables)  # a mistyped --var before the file is opened
    check_regular_file(path)
    hdf5 = _is_hdf5(path)
    try:
        if hdf5:  # plain HDF5 datasets have no dimension names
            ds = xr.open_dataset(path, engine="h5netcdf", decode_times=False, decode_timedelta=False, cache=False,
                                 phony_dims="access")
        else:
            ds = xr.open_dataset(path, engine="scipy", decode_times=False, decode_timedelta=False, cache=False)
    except Exception as exc:  # h5netcdf, h5py and scipy raise many types for foreign or damaged files
        raise ScanError(f"{path} is not a readable NetCDF/HDF5 file ({_reason(exc)})") from None
    with ds:
        held = [str(v) for v in ds.variables]
        metadata = [v for v in held if ds[v].ndim == 0 or ds[v].dims == (v,)]
        selection = select_variables(str(path), held, variables, metadata)
        chosen = {name: selected.variable for name, selected in selection.items()}
        _check_variable_sizes(path, ds, chosen)
        try:
            arrays = {name: _in_store_units(path, name, ds[s.variable].attrs.get("units"), ds[s.variable].values,
                                            s.degrees)
                      for name, s in selection.items()}
        except ScanError:
            raise
        except Exception as exc:  # a damaged chunk or a failing filter while reading
            raise ScanError(f"{path} cannot be read ({_reason(exc)})") from None
        stored = arrays.pop("frequencies_hz", None)
        if stored is None and "frequencies_hz" in ds.attrs:
            stored = np.atleast_1d(np.asarray(ds.attrs["frequencies_hz"]))
        wrap = {name: arrays.pop(name, None) for name in ("speed_of_light_m_per_s", "wrap_period_m")}
        for name, value in wrap.items():
            if value is None and name in ds.attrs:
                wrap[name] = np.atleast_1d(np.asarray(ds.attrs[name]))
    if frequencies_hz is not None:
        freqs: tuple[float, ...] | NDArray = frequencies_hz
    elif stored is not None:
        freqs = stored_frequencies(path, stored)
    else:
        raise ScanError(f"{path} holds no frequencies_hz variable or attribute; pass --frequencies")
    frequencies = tuple(float(f) for f in freqs)
    c = speed_of_light_of(str(path), frequencies, wrap["speed_of_light_m_per_s"], wrap["wrap_period_m"],
                          speed_of_light_m_per_s)
    return import_arrays(path.stem, frequencies, arrays, c, source=str(path))


def _reason(exc: Exception) -> str:
    text = str(exc).strip().splitlines()
    return f"{type(exc).__name__}: {text[0]}" if text else type(exc).__name__


def _is_hdf5(path: Path) -> bool:
    """Whether the file is NetCDF-4/HDF5 (read with h5netcdf) rather than NetCDF-3 (scipy), from its first bytes."""
    try:
        with path.open("rb") as stream:
            magic = stream.read(len(_HDF5_MAGIC))
    except OSError as exc:
        raise ScanError(f"cannot read {path}: {exc.strerror or exc}") from None
    if magic == _HDF5_MAGIC:
        return True
    if magic.startswith(_NETCDF3_MAGIC):
        return False
    raise ScanError(f"{path} is neither NetCDF nor HDF5 (it does not start with their signature)")


def _check_variable_sizes(path: Path, ds: xr.Dataset, chosen: Mapping[str, str]) -> None:
    """Numbers and booleans only, within the memory budget of a scan, before any variable is read."""
    for name, variable in chosen.items():
        if ds[variable].dtype.kind not in "biuf":
            raise ScanError(f"{path}: variable {variable!r} ({name}) has dtype {ds[variable].dtype}; only numbers "
                            "and booleans can be imported")
    check_memory_budget(path, [(f"variable {v!r}", ds[v].shape, ds[v].dtype) for v in chosen.values()])


def _in_store_units(path: Path, name: str, units: object, values: NDArray, degrees: bool = False) -> NDArray:
    """``values`` converted from their declared ``units`` to the unit of the scan store (see :data:`UNITS`);
    with ``degrees`` (a ``_deg`` name) the values are degrees, and a ``units`` attribute must agree."""
    if degrees:
        if units is not None and _RADIANS.get(str(units).strip().lower()) != _RADIANS["degrees"]:
            raise ScanError(f"{path}: {name} is mapped as degrees but its variable has units {units!r}; map it as "
                            f"{name} instead")
        units = "degrees"
    if name not in UNITS or units is None:
        return values
    unit, factors = UNITS[name]
    factor = factors.get(str(units).strip().lower())
    if factor is None:
        raise ScanError(f"{path}: {name} has units {units!r}; give it in {unit} or one of "
                        f"{', '.join(sorted(factors))}")
    return values if factor == 1.0 else values * factor
