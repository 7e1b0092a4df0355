"""Importers of other tools' files into scans, one module per format (as xarray's backends), and the
registry that picks one by suffix: :func:`load_scan_file`, and the batch import of :func:`find_scan_files`,
:func:`plan_import` and :func:`import_files`.

The interface every importer keeps is :class:`~mpi_lidar.scans.importers.base.ScanImporter`.
"""

from __future__ import annotations

import glob
from collections.abc import Callable, Mapping, Sequence
from dataclasses import replace
from pathlib import Path

from mpi_lidar.scans.importers.base import SCAN_VARIABLES, ScanImporter, check_variables, import_arrays
from mpi_lidar.scans.importers.netcdf import NetcdfImporter, load_netcdf
from mpi_lidar.scans.importers.npz import NpzImporter, load_npz
from mpi_lidar.scans.scan import Scan, ScanError
from mpi_lidar.scans.store import MAX_SCAN_BYTES, SCAN_SUFFIX, write_scan

__all__ = ["IMPORTERS", "IMPORT_SUFFIXES", "SCAN_VARIABLES", "ScanImporter", "check_variables", "find_scan_files",
           "import_arrays", "import_files", "importer_for", "load_netcdf", "load_npz", "load_scan_file",
           "plan_import"]

# The importers, in the order their suffixes are listed to the user.
IMPORTERS: tuple[ScanImporter, ...] = (NpzImporter(), NetcdfImporter())
IMPORT_SUFFIXES = tuple(suffix for importer in IMPORTERS for suffix in importer.suffixes)


def importer_for(path: Path) -> ScanImporter | None:
    """The importer of a file by its suffix (any case), or None."""
    suffix = path.suffix.lower()
    return next((importer for importer in IMPORTERS if suffix in importer.suffixes), None)


def load_scan_file(path: str | Path, frequencies_hz: tuple[float, ...] | None = None,
                   variables: Mapping[str, str] | None = None) -> Scan:
    """Import one file by its suffix: ``.npz`` (:func:`load_npz`), ``.nc``/``.h5``/``.hdf5`` (:func:`load_netcdf`)."""
    path = Path(path)
    importer = importer_for(path)
    if importer is None:
        raise ScanError(f"{path}: cannot import {path.suffix.lower() or 'a file without suffix'}; give "
                        f"{', '.join(IMPORT_SUFFIXES)}")
    return importer.load(path, frequencies_hz, variables)


def find_scan_files(sources: Sequence[str | Path]) -> list[Path]:
    """The files named directly, found in a directory (not recursively) or matched by a glob, in order, once.

    A source that names nothing importable is an error, so a mistyped path or pattern is never silently empty.
    """
    found: list[Path] = []
    for source in sources:
        path = Path(source)
        if path.is_dir():
            matches = sorted(p for p in path.iterdir() if _importable(p))
        elif path.exists():
            matches = [path]
        elif glob.has_magic(str(source)):
            matches = sorted(p for p in map(Path, glob.glob(str(source))) if _importable(p))
        else:
            raise ScanError(f"{source} does not exist")
        if not matches:
            raise ScanError(f"{source} holds or matches no {', '.join(IMPORT_SUFFIXES)} file")
        found += matches
    unique: dict[Path, Path] = {}
    for path in found:
        unique.setdefault(path.resolve(), path)
    return list(unique.values())


def _importable(path: Path) -> bool:
    return path.is_file() and path.suffix.lower() in IMPORT_SUFFIXES and not path.name.startswith(".")


def plan_import(files: Sequence[Path], out: str | Path) -> list[tuple[Path, Path]]:
    """(source, store) pairs: ``out`` itself for one file and an ``out`` ending in ``.scan.zarr``, else
    ``out/<stem>.scan.zarr`` per file. Two files for one store, or a store that exists, are refused."""
    out = Path(out)
    if out.name.endswith(SCAN_SUFFIX):
        if len(files) != 1:
            raise ScanError(f"--out {out} is one scan store, but {len(files)} files were given; give a directory "
                            f"as --out to write <dir>/<name>{SCAN_SUFFIX} for each")
        plan = [(Path(files[0]), out)]
    else:
        if out.exists() and not out.is_dir():
            raise ScanError(f"--out {out} exists and is not a directory")
        plan = [(Path(f), out / f"{Path(f).stem}{SCAN_SUFFIX}") for f in files]
    targets: dict[Path, Path] = {}
    for source, target in plan:
        if target in targets:
            raise ScanError(f"{targets[target]} and {source} would both be written to {target}; import them "
                            "into different directories")
        targets[target] = source
        if target.exists() or target.is_symlink():
            raise ScanError(f"{target} already exists; choose another --out or remove it")
    return plan


def import_files(plan: Sequence[tuple[Path, Path]], frequencies_hz: tuple[float, ...] | None = None,
                 variables: Mapping[str, str] | None = None,
                 on_scan: Callable[[Scan, Path], None] | None = None, depth_wrapped: bool = True) -> list[Path]:
    """Import every (source, store) pair of :func:`plan_import`: all or nothing.

    ``depth_wrapped``: whether the files' depths are each frequency's wrapped depth (a phase's, the default)
    or one range the scanner unwrapped already; the stores record it (:attr:`Scan.depth_wrapped`).

    Every file is read and validated before the first store is written, so one bad file refuses the whole
    import with its error and nothing is written. Scans that fit :data:`MAX_SCAN_BYTES` together are kept
    from the first pass; the others are read again to be written. ``on_scan(scan, store)`` after each write.
    """
    loaded: list[Scan | None] = []
    held = 0
    for source, _ in plan:
        scan = load_scan_file(source, frequencies_hz, variables)
        size = scan.depth.nbytes + scan.amplitude.nbytes + (0 if scan.taps is None else scan.taps.nbytes)
        keep = held + size <= MAX_SCAN_BYTES
        held += size if keep else 0
        loaded.append(scan if keep else None)
    written = []
    for (source, target), kept in zip(plan, loaded, strict=True):
        scan = kept if kept is not None else load_scan_file(source, frequencies_hz, variables)
        scan = replace(scan, depth_wrapped=depth_wrapped)
        written.append(write_scan(scan, target))
        if on_scan is not None:
            on_scan(scan, target)
    return written
