"""Importers of other tools' files into scans, one module per format (as xarray's backends), and the
registry that picks one by suffix: :func:`load_scan_file`, and the batch import of :func:`find_scan_files`,
:func:`plan_import`, :func:`new_stores` and :func:`import_files`.

The interface every importer keeps is :class:`~mpi_lidar.scans.importers.base.ScanImporter`.
"""

from __future__ import annotations

import contextlib
import glob
import os
import shutil
import uuid
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import replace
from pathlib import Path

from mpi_lidar.scans.importers.base import (
    MAX_FILE_BYTES,
    SCAN_VARIABLES,
    ScanImporter,
    check_regular_file,
    check_variables,
    import_arrays,
    select_variables,
)
from mpi_lidar.scans.importers.netcdf import NetcdfImporter, load_netcdf
from mpi_lidar.scans.importers.npz import NpzImporter, load_npz
from mpi_lidar.scans.importers.zarr_group import ZarrImporter, is_zarr_group, load_zarr, zarr_scan_name
from mpi_lidar.scans.scan import Scan, ScanError, check_wrap_periods
from mpi_lidar.scans.store import MAX_SCAN_BYTES, SCAN_SUFFIX, read_scan, write_scan

__all__ = ["IMPORTERS", "IMPORT_SUFFIXES", "MAX_FILE_BYTES", "SCAN_VARIABLES", "ScanImporter", "check_regular_file",
           "check_variables", "find_scan_files", "import_arrays", "import_files", "importer_for", "load_netcdf",
           "load_npz", "load_scan_file", "load_zarr", "new_stores", "plan_import", "select_variables"]

# The importers, in the order their suffixes are listed to the user.
IMPORTERS: tuple[ScanImporter, ...] = (NpzImporter(), NetcdfImporter(), ZarrImporter())
IMPORT_SUFFIXES = tuple(suffix for importer in IMPORTERS for suffix in importer.suffixes)


def importer_for(path: Path) -> ScanImporter | None:
    """The importer of a file by its suffix (any case), or None."""
    suffix = path.suffix.lower()
    return next((importer for importer in IMPORTERS if suffix in importer.suffixes), None)


def load_scan_file(path: str | Path, frequencies_hz: tuple[float, ...] | None = None,
                   variables: Mapping[str, str] | None = None, speed_of_light_m_per_s: float | None = None) -> Scan:
    """Import one file by its suffix: ``.npz`` (:func:`load_npz`), ``.nc``/``.h5``/``.hdf5`` (:func:`load_netcdf`),
    or a Zarr group's directory ``.zarr`` (:func:`load_zarr`).

    Only a regular file of at most :data:`MAX_FILE_BYTES` (a directory holding a Zarr group for ``.zarr``) is
    opened (every importer checks it with its ``check_source`` first).
    """
    path = Path(path)
    importer = importer_for(path)
    if importer is None:
        raise ScanError(f"{path}: cannot import {path.suffix.lower() or 'a file without suffix'}; give "
                        f"{', '.join(IMPORT_SUFFIXES)}")
    return importer.load(path, frequencies_hz, variables, speed_of_light_m_per_s)


def find_scan_files(sources: Sequence[str | Path]) -> list[Path]:
    """The files named directly, found in a directory (not recursively) or matched by a glob, in order, once.

    A Zarr group (a directory with its metadata) named directly is one source; a directory that is not one is
    searched. A source that names nothing importable is an error, so a mistyped path or pattern is never
    silently empty; so is any path found that its importer cannot read safely (:func:`check_regular_file`: a
    FIFO, a device or a link to one; a ``.zarr`` that is not a Zarr group), before any file is opened.
    """
    found: list[Path] = []
    for source in sources:
        path = Path(source)
        if is_zarr_group(path):
            matches = [path]
        elif path.is_dir():
            matches = sorted(p for p in path.iterdir() if _importable(p))
        elif path.exists():
            matches = [path]
        elif glob.has_magic(str(source)):
            matches = sorted(p for p in map(Path, glob.glob(str(source))) if _importable(p))
        else:
            raise ScanError(f"{source} does not exist")
        if not matches:
            raise ScanError(f"{source} holds or matches no {', '.join(IMPORT_SUFFIXES)} file")
        for match in matches:
            importer = importer_for(match)
            if importer is None:
                raise ScanError(f"{match}: cannot import {match.suffix.lower() or 'a file without suffix'}; give "
                                f"{', '.join(IMPORT_SUFFIXES)}")
            importer.check_source(match)
        found += matches
    unique: dict[Path, Path] = {}
    for path in found:
        unique.setdefault(path.resolve(), path)
    return list(unique.values())


def _importable(path: Path) -> bool:
    """A name to import (then checked to be a regular file): an import suffix, not hidden."""
    return path.suffix.lower() in IMPORT_SUFFIXES and not path.name.startswith(".")


def store_name(path: Path) -> str:
    """The name of the scan store a file is imported into: ``<name>.scan.zarr``, ``<name>`` the file's name
    without its suffix (without ``.scan.zarr`` or ``.zarr`` for a Zarr group)."""
    stem = zarr_scan_name(path) if path.suffix.lower() == ".zarr" else path.stem
    return f"{stem}{SCAN_SUFFIX}"


def plan_import(files: Sequence[Path], out: str | Path) -> list[tuple[Path, Path]]:
    """(source, store) pairs: ``out`` itself for one file and an ``out`` ending in ``.scan.zarr``, else
    ``out/<name>.scan.zarr`` per file (:func:`store_name`). Two files for one store are refused, and so is an
    ``out`` store that exists; in a directory, stores that exist already are for :func:`new_stores` to set
    apart."""
    out = Path(out)
    if out.name.endswith(SCAN_SUFFIX):
        if len(files) != 1:
            raise ScanError(f"--out {out} is one scan store, but {len(files)} files were given; give a directory "
                            f"as --out to write <dir>/<name>{SCAN_SUFFIX} for each")
        plan = [(Path(files[0]), out)]
    else:
        if out.exists() and not out.is_dir():
            raise ScanError(f"--out {out} exists and is not a directory")
        plan = [(Path(f), out / store_name(Path(f))) for f in files]
    targets: dict[Path, Path] = {}
    for source, target in plan:
        if target in targets:
            raise ScanError(f"{targets[target]} and {source} would both be written to {target}; import them "
                            "into different directories")
        targets[target] = source
    if out.name.endswith(SCAN_SUFFIX) and (out.exists() or out.is_symlink()):
        raise ScanError(f"{out} already exists; choose another --out or remove it")
    return plan


def new_stores(plan: Sequence[tuple[Path, Path]]) -> tuple[list[tuple[Path, Path]], list[tuple[Path, Path]]]:
    """The pairs of a plan whose store does not exist yet, and those whose store does (an earlier import into
    the same directory): more files are added to an import directory, never over a store already there. A plan
    whose every store exists is refused with one line naming the first."""
    existing = [(source, target) for source, target in plan if target.exists() or target.is_symlink()]
    if existing and len(existing) == len(plan):
        source, target = existing[0]
        more = f" (and the {len(existing) - 1} others')" if len(existing) > 1 else ""
        raise ScanError(f"{target} already exists{more}, so {source} was not imported; nothing was new: remove a "
                        "store to import its file again, or choose another --out")
    return [pair for pair in plan if pair not in existing], existing


def import_files(plan: Sequence[tuple[Path, Path]], frequencies_hz: tuple[float, ...] | None = None,
                 variables: Mapping[str, str] | None = None,
                 on_scan: Callable[[Scan, Path], None] | None = None, depth_wrapped: bool = True,
                 speed_of_light_m_per_s: float | None = None) -> list[Path]:
    """Import every (source, store) pair of :func:`plan_import`: all or nothing.

    ``depth_wrapped``: whether the files' depths are each frequency's wrapped depth (a phase's, the default)
    or one range the scanner unwrapped already; the stores record it (:attr:`Scan.depth_wrapped`).
    ``speed_of_light_m_per_s``: the speed of light the scanner converted phase to range with [m/s], where the
    files do not say (else the physical 299,792,458 m/s); a wrapped depth beyond its frequency's wrap period
    c / 2f refuses the import (:func:`~mpi_lidar.scans.scan.check_wrap_periods`).

    Every file is read and validated before the first store is written, so one bad file refuses the whole
    import with its error and nothing is written. Scans that fit :data:`MAX_SCAN_BYTES` together are kept
    from the first pass; the others are read again to be written. Each store is written under a staging name
    beside its target (``.<name>.writing-<8 hex>``, which
    :func:`~mpi_lidar.storage.atomic.remove_interrupted_staging` recognises), and only when all are written
    are they renamed into place; a failure on the way (a write, a rename, a target that appeared meanwhile)
    removes the stagings, the stores already renamed and the directories this call created, so the import
    leaves all its stores or none. ``on_scan(scan, store)`` for each store once all are in place (a scan not
    kept from the first pass is read back from its store for it).
    """
    loaded: list[Scan | None] = []
    held = 0
    def load(source: Path) -> Scan:
        scan = replace(load_scan_file(source, frequencies_hz, variables, speed_of_light_m_per_s),
                       depth_wrapped=depth_wrapped)
        check_wrap_periods(scan, str(source))
        return scan

    for source, _ in plan:
        scan = load(source)
        size = scan.depth.nbytes + scan.amplitude.nbytes + (0 if scan.taps is None else scan.taps.nbytes)
        keep = held + size <= MAX_SCAN_BYTES
        held += size if keep else 0
        loaded.append(scan if keep else None)
    for _, target in plan:
        if target.exists() or target.is_symlink():
            raise ScanError(f"{target} already exists; choose another --out or remove it")
    created = _missing_directories(target.parent for _, target in plan)
    staged: list[tuple[Path, Path]] = []
    published: list[Path] = []
    try:
        for (source, target), kept in zip(plan, loaded, strict=True):
            scan = kept if kept is not None else load(source)
            staging = target.parent / f".{target.name}.writing-{uuid.uuid4().hex[:8]}"
            staged.append((staging, target))
            try:
                write_scan(scan, staging)
            except ScanError as exc:  # name the store the user asked for, not its staging name
                raise ScanError(str(exc).replace(str(staging), str(target))) from None
        for staging, target in staged:
            if target.exists() or target.is_symlink():
                raise ScanError(f"{target} appeared while importing; nothing was imported: choose another --out "
                                "or remove it")
            try:
                os.rename(staging, target)
            except OSError as exc:
                raise ScanError(f"cannot write scan {target}: {exc.strerror or exc}; choose a writable path with "
                                "free space") from None
            published.append(target)
    except BaseException:
        for path in [*published, *(staging for staging, _ in staged)]:
            _remove_tree(path)
        for directory in reversed(created):
            with contextlib.suppress(OSError):  # only if nothing else was put there meanwhile
                directory.rmdir()
        raise
    if on_scan is not None:
        for (_, target), kept in zip(plan, loaded, strict=True):
            on_scan(kept if kept is not None else read_scan(target, stored_above_bytes=0), target)
    return published


def _missing_directories(parents: Iterable[Path]) -> list[Path]:
    """The directories of ``parents`` and their ancestors that do not exist yet, outermost first."""
    missing: list[Path] = []
    for parent in parents:
        for directory in reversed([parent, *parent.parents]):
            if not directory.exists() and directory not in missing:
                missing.append(directory)
    return missing


def _remove_tree(path: Path) -> None:
    if path.is_symlink() or path.is_file():
        path.unlink(missing_ok=True)
    elif path.exists():
        shutil.rmtree(path, ignore_errors=True)
