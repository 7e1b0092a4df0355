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
    check_variables,
    import_arrays,
    stored_frequencies,
)
from mpi_lidar.scans.scan import Scan, ScanError
from mpi_lidar.scans.store import check_memory_budget


class NpzImporter(ScanImporter):
    """``.npz`` archives (:func:`load_npz`)."""

    suffixes: ClassVar[tuple[str, ...]] = (".npz",)

    def load(self, path: Path, frequencies_hz: tuple[float, ...] | None = None,
             variables: Mapping[str, str] | None = None) -> Scan:
        return load_npz(path, frequencies_hz, variables)


def load_npz(path: str | Path, frequencies_hz: tuple[float, ...] | None = None,
             variables: Mapping[str, str] | None = None) -> Scan:
    """Import an ``.npz`` archive (arrays named as in the scan store; frequencies_hz inside or given).

    ``variables`` maps scan array names to the archive's member names (``{"depth": "range_m"}``); members
    it does not name must be named as in the scan store. Every member's header is checked (dtype, declared
    size against the memory budget) before any array is read, so a damaged or hostile archive is refused
    without allocating what it claims.
    """
    path = Path(path)
    variables = check_variables(variables)
    _check_npz_headers(path)
    try:
        with np.load(path, allow_pickle=False) as archive:
            arrays = {key: archive[key] for key in archive.files}
    except Exception as exc:  # zipfile, numpy and OS errors of a damaged archive
        raise ScanError(f"{path} is not a readable .npz archive ({type(exc).__name__}: {exc})") from None
    arrays = _renamed(path, arrays, variables)
    stored = arrays.pop("frequencies_hz", None)
    if frequencies_hz is not None:
        freqs: tuple[float, ...] | NDArray = frequencies_hz
    elif stored is not None:
        freqs = stored_frequencies(path, stored)
    else:
        raise ScanError(f"{path} holds no frequencies_hz array; pass --frequencies")
    return import_arrays(path.name.removesuffix(".npz"), tuple(float(f) for f in freqs), arrays, source=str(path))


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


def _renamed(path: Path, arrays: dict[str, NDArray], variables: Mapping[str, str]) -> dict[str, NDArray]:
    missing = sorted(f"{name}={member}" for name, member in variables.items() if member not in arrays)
    if missing:
        raise ScanError(f"{path} has no array for --var {', '.join(missing)}; it holds {sorted(arrays)}")
    rest = {key: value for key, value in arrays.items() if key not in set(variables.values())}
    clash = sorted(set(rest) & set(variables))
    if clash:
        raise ScanError(f"{path} holds {clash} itself and --var maps other arrays to them; remove one or the other")
    return {**rest, **{name: arrays[member] for name, member in variables.items()}}

