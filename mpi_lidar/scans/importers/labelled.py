"""What the formats read through xarray share (NetCDF/HDF5 and Zarr): a dataset's variables to a scan
(:func:`scan_from_dataset`), with their declared units converted and the source's attributes kept as provenance
(:func:`provenance`)."""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import replace
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import NDArray

from mpi_lidar.scans.importers.base import (
    WRAP_VARIABLES,
    import_arrays,
    select_variables,
    speed_of_light_of,
    stored_frequencies,
)
from mpi_lidar.scans.scan import Scan, ScanError
from mpi_lidar.scans.store import check_memory_budget

if TYPE_CHECKING:
    import xarray as xr

# Units a variable may declare (its ``units`` attribute), as factors to the store's unit; a variable without
# ``units`` is taken to be in the store's unit already.
_METRES = {"m": 1.0, "meter": 1.0, "meters": 1.0, "metre": 1.0, "metres": 1.0, "cm": 1e-2, "mm": 1e-3, "km": 1e3}
_RADIANS = {"rad": 1.0, "radian": 1.0, "radians": 1.0, "deg": np.pi / 180, "degree": np.pi / 180,
            "degrees": np.pi / 180}
_HERTZ = {"hz": 1.0, "khz": 1e3, "mhz": 1e6, "ghz": 1e9}
_METRES_PER_SECOND = {"m/s": 1.0, "m s-1": 1.0, "m.s-1": 1.0, "m s^-1": 1.0, "km/s": 1e3, "km s-1": 1e3}
UNITS = {"depth": ("m", _METRES), "reference_depth": ("m", _METRES), "azimuth_rad": ("rad", _RADIANS),
         "elevation_rad": ("rad", _RADIANS), "frequencies_hz": ("Hz", _HERTZ), "wrap_period_m": ("m", _METRES),
         "speed_of_light_m_per_s": ("m/s", _METRES_PER_SECOND)}
# The source's attributes that become scan settings rather than provenance.
_READ_ATTRIBUTES = ("frequencies_hz", *WRAP_VARIABLES)
# Provenance kept per value: strings up to this many characters, arrays up to this many elements.
_MAX_TEXT = 1000
_MAX_ELEMENTS = 64


def scan_from_dataset(path: Path, ds: xr.Dataset, name: str, file_format: str,
                      frequencies_hz: tuple[float, ...] | None = None, variables: Mapping[str, str] | None = None,
                      speed_of_light_m_per_s: float | None = None) -> Scan:
    """The scan in an opened dataset (lazy: nothing is read before the dtypes and sizes are checked).

    Variables are chosen by :func:`~mpi_lidar.scans.importers.base.select_variables` (a dimension coordinate, a
    variable named like its only dimension, or a scalar is metadata, never refused); ``units`` attributes are
    converted (:data:`UNITS`); the frequencies come from ``frequencies_hz``, else the variable ``frequencies_hz``
    (or ``frequency_hz``), else the attribute ``frequencies_hz``; the speed of light from the variable or
    attribute ``speed_of_light_m_per_s`` or ``wrap_period_m``, or ``speed_of_light_m_per_s`` given. The scan's
    ``scene`` keeps the dataset's other attributes and scalar variables (:func:`provenance`).
    """
    held = [str(v) for v in ds.variables]
    metadata = [v for v in held if ds[v].ndim == 0 or ds[v].dims == (v,)]
    selection = select_variables(str(path), held, variables, metadata)
    chosen = {scan_name: selected.variable for scan_name, selected in selection.items()}
    _check_variable_sizes(path, ds, chosen)
    try:
        arrays = {scan_name: in_store_units(path, scan_name, ds[s.variable].attrs.get("units"),
                                            ds[s.variable].values, s.degrees)
                  for scan_name, s in selection.items()}
    except ScanError:
        raise
    except Exception as exc:  # a damaged chunk or a failing filter while reading
        raise ScanError(f"{path} cannot be read ({reason(exc)})") from None
    stored = arrays.pop("frequencies_hz", None)
    if stored is None and "frequencies_hz" in ds.attrs:
        stored = np.atleast_1d(np.asarray(ds.attrs["frequencies_hz"]))
    wrap = {key: arrays.pop(key, None) for key in WRAP_VARIABLES}
    for key, value in wrap.items():
        if value is None and key in ds.attrs:
            wrap[key] = np.atleast_1d(np.asarray(ds.attrs[key]))
    kept = provenance(path, file_format, ds, [v for v in metadata if v not in chosen.values()])
    if frequencies_hz is not None:
        freqs: tuple[float, ...] | NDArray = frequencies_hz
    elif stored is not None:
        freqs = stored_frequencies(path, stored)
    else:
        raise ScanError(f"{path} holds no frequencies_hz variable or attribute; pass --frequencies")
    frequencies = tuple(float(f) for f in freqs)
    c = speed_of_light_of(str(path), frequencies, wrap["speed_of_light_m_per_s"], wrap["wrap_period_m"],
                          speed_of_light_m_per_s)
    scan = import_arrays(name, frequencies, arrays, c, source=str(path))
    return replace(scan, scene={**scan.scene, **kept})


def provenance(path: Path, file_format: str, ds: xr.Dataset, scalars: list[str]) -> dict[str, object]:
    """Where a scan came from, for its ``scene`` metadata: ``{"source": {"file", "format", "attributes",
    "scalars"}}``, with the dataset's global attributes (e.g. ``instrument``, ``serial``; not those read as
    scan settings) and its scalar variables (e.g. a ``timestamp``, with its own attributes such as ``units``).
    Values are kept as JSON (numbers, strings, short lists); others are left out."""
    attributes = {str(k): v for k, v in ((k, _json_value(v)) for k, v in ds.attrs.items()
                                         if k not in _READ_ATTRIBUTES) if v is not None}
    found: dict[str, object] = {}
    for variable in scalars:
        if ds[variable].ndim != 0 or ds[variable].dtype.kind not in "biufUSO":
            continue
        value = _json_value(ds[variable].values)
        if value is not None:
            found[variable] = {"value": value, **{str(k): v for k, v in
                                                  ((k, _json_value(v)) for k, v in ds[variable].attrs.items())
                                                  if v is not None}}
    source: dict[str, object] = {"file": path.name, "format": file_format}
    if attributes:
        source["attributes"] = attributes
    if found:
        source["scalars"] = found
    return {"source": source}


def _json_value(value: object) -> object | None:
    """``value`` as JSON (a number, string, bool or short list of them), or None where it is none of those."""
    if isinstance(value, bytes):
        value = value.decode("utf-8", errors="replace")
    if isinstance(value, str):
        return value[:_MAX_TEXT]
    array = np.asarray(value)
    if array.dtype.kind in "US":
        return _json_value(array.item()) if array.ndim == 0 else None
    if array.dtype.kind not in "biuf" or array.size > _MAX_ELEMENTS:
        return None
    if array.dtype.kind == "f" and not np.isfinite(array).all():
        return None  # NaN and infinities are not JSON
    return array.item() if array.ndim == 0 else array.tolist()


def reason(exc: Exception) -> str:
    """The first line of an exception of a reader, with its type."""
    text = str(exc).strip().splitlines()
    return f"{type(exc).__name__}: {text[0]}" if text else type(exc).__name__


def _check_variable_sizes(path: Path, ds: xr.Dataset, chosen: Mapping[str, str]) -> None:
    """Numbers and booleans only, within the memory budget of a scan, before any variable is read."""
    for scan_name, variable in chosen.items():
        if ds[variable].dtype.kind not in "biuf":
            raise ScanError(f"{path}: variable {variable!r} ({scan_name}) has dtype {ds[variable].dtype}; only "
                            "numbers and booleans can be imported")
    check_memory_budget(path, [(f"variable {v!r}", ds[v].shape, ds[v].dtype) for v in chosen.values()])


def in_store_units(path: Path, name: str, units: object, values: NDArray, degrees: bool = False) -> NDArray:
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
