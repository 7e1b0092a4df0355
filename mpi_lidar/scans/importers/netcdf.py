"""NetCDF (3 or 4) and HDF5 files, read through xarray."""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import ClassVar

from mpi_lidar.scans.importers.base import ScanImporter, check_regular_file, check_variables
from mpi_lidar.scans.importers.labelled import reason, scan_from_dataset
from mpi_lidar.scans.scan import Scan, ScanError

__all__ = ["NetcdfImporter", "load_netcdf"]

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
    The file's global attributes (e.g. ``instrument``, ``serial``) and scalar variables (e.g. a ``timestamp``) are
    kept in the scan's ``scene`` metadata under ``source``
    (:func:`~mpi_lidar.scans.importers.labelled.provenance`).
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
        raise ScanError(f"{path} is not a readable NetCDF/HDF5 file ({reason(exc)})") from None
    with ds:
        return scan_from_dataset(path, ds, path.stem, "hdf5" if hdf5 else "netcdf3", frequencies_hz, variables,
                                 speed_of_light_m_per_s)


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
