"""Zarr groups (v2 or v3) written by another tool: a directory ``*.zarr``, read through xarray."""

from __future__ import annotations

import stat
import warnings
from collections.abc import Mapping
from pathlib import Path
from typing import TYPE_CHECKING, ClassVar

from mpi_lidar.scans.importers.base import ScanImporter, check_variables
from mpi_lidar.scans.importers.labelled import reason, scan_from_dataset
from mpi_lidar.scans.scan import Scan, ScanError
from mpi_lidar.scans.store import SCAN_SUFFIX

if TYPE_CHECKING:
    import xarray as xr

__all__ = ["ZarrImporter", "is_zarr_group", "load_zarr"]

# The file that makes a directory a Zarr group: v3's zarr.json, v2's .zgroup.
GROUP_FILES = ("zarr.json", ".zgroup")


class ZarrImporter(ScanImporter):
    """Zarr groups (:func:`load_zarr`): a directory, not a file."""

    suffixes: ClassVar[tuple[str, ...]] = (".zarr",)

    def check_source(self, path: Path) -> None:
        check_zarr_group(path)

    def load(self, path: Path, frequencies_hz: tuple[float, ...] | None = None,
             variables: Mapping[str, str] | None = None, speed_of_light_m_per_s: float | None = None) -> Scan:
        return load_zarr(path, frequencies_hz, variables, speed_of_light_m_per_s)


def is_zarr_group(path: Path) -> bool:
    """Whether ``path`` is a directory holding a Zarr group's metadata (v3 ``zarr.json`` or v2 ``.zgroup``)."""
    return path.is_dir() and any((path / name).is_file() for name in GROUP_FILES)


def check_zarr_group(path: Path) -> None:
    """Refuse, before anything is read, a path that is not a directory holding a Zarr group."""
    try:
        mode = path.stat().st_mode
    except FileNotFoundError:
        raise ScanError(f"{path} does not exist") from None
    except OSError as exc:
        raise ScanError(f"cannot read {path}: {exc.strerror or exc}") from None
    if not stat.S_ISDIR(mode) or not is_zarr_group(path):
        raise ScanError(f"{path} is not a Zarr group (a directory with zarr.json or .zgroup); give the group's "
                        "directory")


def load_zarr(path: str | Path, frequencies_hz: tuple[float, ...] | None = None,
              variables: Mapping[str, str] | None = None, speed_of_light_m_per_s: float | None = None) -> Scan:
    """Import a Zarr group (v2 or v3) another tool wrote, as :func:`~mpi_lidar.scans.importers.load_netcdf`
    imports a NetCDF file: its arrays named as in the scan store (or an alias) or mapped by ``variables``
    (``--var``), ``units`` attributes converted, the frequencies and speed of light from its arrays or
    attributes (or given), its other attributes and scalar arrays kept in the scan's ``scene`` metadata under
    ``source``. Arrays without dimension names (a group written with zarr alone) are read with one dimension
    name per array axis. Each chosen array's dtype and declared size are checked against the memory budget
    before any chunk is read.
    """
    path = Path(path)
    check_variables(variables)  # a mistyped --var before the store is opened
    check_zarr_group(path)
    ds = _open(path)
    with ds:
        return scan_from_dataset(path, ds, zarr_scan_name(path), "zarr", frequencies_hz, variables,
                                 speed_of_light_m_per_s)


def zarr_scan_name(path: Path) -> str:
    """A group's scan name: its directory name without ``.scan.zarr`` or ``.zarr``."""
    return path.name.removesuffix(SCAN_SUFFIX).removesuffix(".zarr")


def _open(path: Path) -> xr.Dataset:
    """The group as a lazy dataset: through xarray's Zarr backend where its arrays name their dimensions,
    else each array wrapped lazily (dask) with dimensions ``<array>_<axis>``."""
    import xarray as xr

    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # zarr warns of v3 consolidated metadata it does not use here
            return xr.open_zarr(path, chunks=None, consolidated=False, decode_times=False, decode_timedelta=False)
    except KeyError:  # no dimension names: read below
        pass
    except Exception as exc:  # zarr raises many types for foreign or damaged metadata
        raise ScanError(f"{path} is not a readable Zarr group ({reason(exc)})") from None
    return _without_dimension_names(path)


def _without_dimension_names(path: Path) -> xr.Dataset:
    import dask.array as da
    import xarray as xr
    import zarr

    try:
        group = zarr.open_group(store=str(path), mode="r", use_consolidated=False)
        arrays = dict(group.arrays())
        return xr.Dataset(
            {name: ((), array[()], dict(array.attrs)) if array.ndim == 0 else
             ([f"{name}_{axis}" for axis in range(array.ndim)], da.from_zarr(array), dict(array.attrs))
             for name, array in arrays.items()},
            attrs=dict(group.attrs))
    except Exception as exc:  # zarr raises many types for foreign or damaged metadata
        raise ScanError(f"{path} is not a readable Zarr group ({reason(exc)})") from None
