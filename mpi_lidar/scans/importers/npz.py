"""NumPy ``.npz`` archives: arrays named as in the scan store, ``frequencies_hz`` inside or given."""

from __future__ import annotations

import zipfile
from collections.abc import Mapping
from pathlib import Path
from typing import ClassVar

import numpy as np
from numpy.typing import DTypeLike, NDArray

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


class NpzImporter(ScanImporter):
    """``.npz`` archives (:func:`load_npz`)."""

    suffixes: ClassVar[tuple[str, ...]] = (".npz",)

    def load(self, path: Path, frequencies_hz: tuple[float, ...] | None = None,
             variables: Mapping[str, str] | None = None, speed_of_light_m_per_s: float | None = None) -> Scan:
        return load_npz(path, frequencies_hz, variables, speed_of_light_m_per_s)


def load_npz(path: str | Path, frequencies_hz: tuple[float, ...] | None = None,
             variables: Mapping[str, str] | None = None, speed_of_light_m_per_s: float | None = None) -> Scan:
    """Import an ``.npz`` archive (arrays named as in the scan store; frequencies_hz inside or given).

    The speed of light the depths were converted with [m/s] is the member ``speed_of_light_m_per_s`` (a scalar),
    or that of the member ``wrap_period_m`` (each frequency's c / 2f [m]), or ``speed_of_light_m_per_s`` given,
    else 299,792,458 m/s (:func:`~mpi_lidar.scans.importers.base.speed_of_light_of`).

    ``variables`` maps scan array names to the archive's member names (``{"depth": "range_m"}``,
    ``{"azimuth_deg": "az"}`` for degrees, ``{"ignore": "notes"}`` to leave members out); members it does not
    name must be named as in the scan store (or an alias: ``azimuth``, ``elevation`` in radians,
    ``azimuth_deg``, ``elevation_deg``), and any other member is refused
    (:func:`~mpi_lidar.scans.importers.base.select_variables`). Every member's header is checked (dtype, declared
    size against the memory budget) before any array is read, so a damaged or hostile archive is refused
    without allocating what it claims.
    """
    path = Path(path)
    check_variables(variables)  # a mistyped --var before the file is opened
    check_regular_file(path)
    _check_npz_headers(path)
    try:
        with np.load(path, allow_pickle=False) as archive:
            chosen = select_variables(str(path), archive.files, variables)
            arrays = {name: archive[selected.variable] for name, selected in chosen.items()}
    except ScanError:
        raise
    except Exception as exc:  # zipfile, numpy and OS errors of a damaged archive
        raise ScanError(f"{path} is not a readable .npz archive ({type(exc).__name__}: {exc})") from None
    for name, selected in chosen.items():
        if selected.degrees:
            arrays[name] = np.radians(np.asarray(arrays[name], dtype=np.float64))
    stored = arrays.pop("frequencies_hz", None)
    if frequencies_hz is not None:
        freqs: tuple[float, ...] | NDArray = frequencies_hz
    elif stored is not None:
        freqs = stored_frequencies(path, stored)
    else:
        raise ScanError(f"{path} holds no frequencies_hz array; pass --frequencies")
    frequencies = tuple(float(f) for f in freqs)
    c = speed_of_light_of(str(path), frequencies, arrays.pop("speed_of_light_m_per_s", None),
                          arrays.pop("wrap_period_m", None), speed_of_light_m_per_s)
    return import_arrays(path.name.removesuffix(".npz"), frequencies, arrays, c, source=str(path))


def _check_npz_headers(path: Path) -> None:
    """Refuse members that are not plain numeric arrays, or that declare more than a scan may hold."""
    try:
        with zipfile.ZipFile(path) as archive:
            declared: list[tuple[str, tuple[int, ...], DTypeLike]] = []
            for info in archive.infolist():
                with archive.open(info) as member:
                    version = np.lib.format.read_magic(member)
                    read_header = (np.lib.format.read_array_header_1_0 if version == (1, 0)
                                   else np.lib.format.read_array_header_2_0)
                    shape, _, dtype = read_header(member)
                if dtype.hasobject or dtype.kind not in "biuf":
                    raise ScanError(f"{path}: member {info.filename} has dtype {dtype}; only numbers and booleans "
                                    "can be imported")
                declared.append((f"member {info.filename}", shape, dtype))
    except ScanError:
        raise
    except Exception as exc:  # not a zip, a member without an .npy header, a damaged header
        raise ScanError(f"{path} is not a readable .npz archive ({type(exc).__name__}: {exc})") from None
    check_memory_budget(path, declared)
