"""``mpi-lidar verify``: check datasets, scans and corrected outputs chunk by chunk against their fingerprints."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import cast

import zarr

from mpi_lidar.correction import CORRECTED_SCHEMA
from mpi_lidar.errors import StoreError
from mpi_lidar.scans.store import SCAN_SCHEMA, read_scan
from mpi_lidar.simulation import dataset
from mpi_lidar.storage.integrity import IntegrityError, verify_array

CORRECTED_STORE = "corrected.zarr"


@dataclass(frozen=True)
class Verified:
    """A store that passed: what it is, how many chunks were checked, and whether it had fingerprints at all."""

    path: str
    kind: str
    chunks: int
    fingerprinted: bool


def verify_store(path: str | Path) -> Verified:
    """Check one store (a dataset, a scan, a corrected store or a scan's output directory); raise on damage."""
    path = Path(path)
    if path.is_dir() and (path / CORRECTED_STORE).is_dir():
        path = path / CORRECTED_STORE
    schema = _schema(path)
    if schema == dataset.SCHEMA:
        return Verified(str(path), "dataset", dataset.verify_dataset(path),
                        "chunk_sha256" in zarr.open_group(store=str(path), mode="r", use_consolidated=False))
    if schema == SCAN_SCHEMA:
        read_scan(path)
        return _verified_arrays(path, "scan", check=False)
    if schema == CORRECTED_SCHEMA:
        return _verified_arrays(path, "corrected output", check=True)
    raise StoreError(f"{path} is not an mpi-lidar dataset, scan or corrected output (schema {schema!r})")


def _schema(path: Path) -> object:
    if not path.exists():
        raise StoreError(f"{path} does not exist")
    try:
        return zarr.open_group(store=str(path), mode="r").attrs.get("schema")
    except Exception as exc:  # zarr raises several types for foreign or broken metadata
        raise StoreError(f"{path} is not a readable Zarr store ({type(exc).__name__})") from None


def _verified_arrays(path: Path, kind: str, check: bool) -> Verified:
    """Count (and, with ``check``, verify) every chunk of every array against the store's recorded fingerprints."""
    group = zarr.open_group(store=str(path), mode="r", use_consolidated=False)
    fingerprints = group.attrs.get("chunk_sha256")
    fingerprints = fingerprints if isinstance(fingerprints, dict) else None
    chunks = 0
    for name in sorted(group.array_keys()):
        array = cast("zarr.Array", group[name])
        expected = None if fingerprints is None else fingerprints.get(name)
        if fingerprints is not None and expected is None:
            raise IntegrityError(f"{path}: array {name!r} has no recorded fingerprints; the store was altered")
        if check:
            verify_array(array, expected, str(path), name)
        chunks += array.nchunks
    return Verified(str(path), kind, chunks, fingerprints is not None)
