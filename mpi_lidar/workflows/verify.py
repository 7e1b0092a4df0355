"""``mpi-lidar verify``: check datasets, scans and corrected outputs chunk by chunk against their fingerprints.

Every store of a current schema version must record its fingerprints (:mod:`mpi_lidar.storage.integrity`):
one without them, or without some array's, is damaged. A scan's output directory is checked whole: its
``corrected.zarr`` chunk by chunk, and every file its manifest lists (:mod:`mpi_lidar.storage.manifest`).
Declared shapes and chunk files are checked before anything is read, and the arrays are read one chunk at a
time, so a store whose metadata declares 100000 x 100000 values is refused without allocating them.

In an object store (``s3://...``) a scan's outputs exist only where published: a ``corrected.zarr`` (or an
output folder) without its manifest fails, and every object the manifest lists is read and its SHA-256
checked (:func:`mpi_lidar.storage.objects.verify_published`). Scans and datasets there are verified as on disk.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import zarr

from mpi_lidar.correction import CORRECTED_SCHEMA
from mpi_lidar.errors import StoreError
from mpi_lidar.locations import Location, location
from mpi_lidar.scans.store import MAX_ARRAY_VALUES, SCAN_SCHEMA, foreign_store_error, read_scan
from mpi_lidar.simulation import dataset
from mpi_lidar.storage.integrity import (
    IntegrityError,
    check_chunk_files,
    check_dimensions,
    check_store_files,
    recorded_fingerprints,
    verified_chunks,
)
from mpi_lidar.storage.manifest import MANIFEST_FILE, is_output_directory, verify_manifest
from mpi_lidar.storage.objects import exists, list_files, verify_published, zarr_store
from mpi_lidar.storage.variables import CORRECTED

CORRECTED_STORE = "corrected.zarr"


@dataclass(frozen=True)
class Verified:
    """A store that passed: what it is, how many chunks (and listed files) were checked, and whether it had
    fingerprints (always, now: a store without them is damaged)."""

    path: str
    kind: str
    chunks: int
    fingerprinted: bool = True
    files: int = 0


def verify_store(path: str | Path) -> Verified:
    """Check one store (a dataset, a scan, a corrected store or a scan's output directory); raise on damage."""
    where = location(path)
    if not where.is_local:
        return _verify_in_store(where)
    path = where.local_path()
    if path.is_dir() and (is_output_directory(path) or (path / CORRECTED_STORE).is_dir()):
        path = path / CORRECTED_STORE  # a scan's output directory: its files, then its store
    outputs = path.parent if path.name == CORRECTED_STORE and is_output_directory(path.parent) else None
    listed = 0 if outputs is None else len(verify_manifest(outputs))
    schema = _schema(path)
    if schema == dataset.SCHEMA:
        return Verified(str(path), "dataset", dataset.verify_dataset(path))
    if schema == SCAN_SCHEMA:
        read_scan(path)
        return _verified_arrays(path, "scan", check=False)
    if schema == CORRECTED_SCHEMA:
        return _verified_arrays(path, "corrected output", check=True, files=listed)
    if schema is None:  # another tool's Zarr store: to import, not damaged
        raise foreign_store_error(path, "no mpi-lidar schema: not a dataset, scan or corrected output")
    raise StoreError(f"{path} is not an mpi-lidar dataset, scan or corrected output (schema {schema!r})")


def _schema(path: Path) -> object:
    if not path.exists():
        raise StoreError(f"{path} does not exist")
    if path.is_dir():
        check_store_files(path)  # links, FIFOs and oversized metadata refused before zarr opens a file
    try:
        return zarr.open_group(store=str(path), mode="r").attrs.get("schema")
    except Exception as exc:  # zarr raises several types for foreign or broken metadata
        raise StoreError(f"{path} is not a readable Zarr store ({type(exc).__name__})") from None


def _verify_in_store(where: Location) -> Verified:
    """:func:`verify_store` of a URL: an output folder or its ``corrected.zarr`` (published), a scan or a dataset."""
    if exists(where.joinpath(MANIFEST_FILE)):
        where = where.joinpath(CORRECTED_STORE)
    folder = where.parent if where.name == CORRECTED_STORE else None
    if folder is not None:
        listed = len(verify_published(folder))  # unpublished (no manifest) or differing: an IntegrityError
        return _verified_arrays(where, "corrected output", check=True, files=listed)
    try:
        schema = _schema_in_store(where)
    except Exception as exc:  # zarr raises several types for foreign or broken metadata
        raise StoreError(f"{where} is not a readable Zarr store ({type(exc).__name__})") from None
    if schema == SCAN_SCHEMA:
        read_scan(where.url)
        return _verified_arrays(where, "scan", check=False)
    if schema == dataset.SCHEMA:
        return Verified(where.url, "dataset", dataset.verify_dataset(where.url))
    raise StoreError(f"{where} is not an mpi-lidar dataset, scan or published corrected output (schema {schema!r})")


def _schema_in_store(where: Location) -> object:
    """The ``schema`` attribute of the store at ``where``, read as Zarr v3 (this package's stores): one request
    where zarr would otherwise probe for Zarr v2 metadata too, three more. Only where there is no ``zarr.json``
    (another tool's store, perhaps v2, or none) is it opened as any format, to say what it is as on disk."""
    try:
        return zarr.open_group(store=zarr_store(where), mode="r", zarr_format=3).attrs.get("schema")
    except FileNotFoundError:
        return zarr.open_group(store=zarr_store(where), mode="r").attrs.get("schema")


def _verified_arrays(path: Path | Location, kind: str, check: bool, files: int = 0) -> Verified:
    """Count (and, with ``check``, verify one chunk at a time) every chunk of every array against the store's
    recorded fingerprints, after its files, declared chunks and shapes passed."""
    found = check_store_files(path) if isinstance(path, Path) else list_files(path)
    try:
        # Only this package's stores come here (their schema read first): Zarr v3, no probe for v2 metadata.
        group = zarr.open_group(store=zarr_store(location(path)), mode="r", use_consolidated=False, zarr_format=3)
        arrays = dict(group.arrays())
        attrs = dict(group.attrs)
    except Exception as exc:  # zarr raises several types for foreign or broken metadata
        raise IntegrityError(f"{path}: its metadata cannot be read ({type(exc).__name__}); the store is damaged: "
                             "restore or regenerate it") from None
    check_chunk_files(str(path), found, arrays)
    fingerprints = recorded_fingerprints(str(path), attrs.get("chunk_sha256"), arrays)
    if check:
        missing = sorted(name for name, v in CORRECTED.items() if v.required and name not in arrays)
        if missing:
            raise IntegrityError(f"{path}: array {missing[0]!r} is gone; the store is damaged: restore it or "
                                 "correct the scan again")
        check_dimensions(str(path), arrays, {name: v.dims for name, v in CORRECTED.items()}, MAX_ARRAY_VALUES)
        for name, array in sorted(arrays.items()):
            for _ in verified_chunks(array, fingerprints[name], str(path), name):
                pass
    return Verified(str(path), kind, sum(array.nchunks for array in arrays.values()), files=files)
