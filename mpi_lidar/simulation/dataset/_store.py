"""The dataset store: creating and opening it, its bookkeeping arrays and writing one chunk of it."""

from __future__ import annotations

import hashlib
import json
import shutil
import tempfile
from collections.abc import Mapping
from contextlib import suppress
from pathlib import Path
from typing import Literal

import numpy as np
import zarr
from numpy.typing import NDArray

from mpi_lidar import __version__
from mpi_lidar.config import Config, config_from_json, config_sha256
from mpi_lidar.errors import StoreError
from mpi_lidar.locations import Location, location
from mpi_lidar.simulation.dataset._chunks import SamplingPlan, simulate_chunk
from mpi_lidar.simulation.dataset._layout import (
    DATA_ARRAYS,
    SCHEMA,
    build_layout,
    check_layout,
    store_array,
)
from mpi_lidar.simulation.sampling import THETA_NAMES
from mpi_lidar.storage.atomic import atomic_path
from mpi_lidar.storage.integrity import check_chunk_files, check_store_files, fingerprint, read_chunk
from mpi_lidar.storage.objects import zarr_store


def create_store(path: str | Path, config: Config) -> zarr.Group:
    """Create an empty dataset store for ``config``, or reopen the one already there for the same config.

    The layout is built under a temporary name beside ``path`` and renamed into place, so a crash never
    leaves a half-made store. A store made from another configuration, or anything at ``path`` that is
    not a dataset store (other than an empty directory), is refused with :class:`StoreError`. ``path`` may be
    an object-store URL (``s3://bucket/prefix/d.zarr``): see :func:`_create_in_object_store`.
    """
    where = location(path)
    if not where.is_local:
        return _create_in_object_store(where, config)
    path = where.local_path()
    if path.exists() and not _is_empty_dir(path):
        group = open_store(path)
        _check_same_config(path, group, config)
        return _writable(where)
    _check_free_space(path, config)
    # Here path is absent or an empty directory, which the new store may replace.
    with atomic_path(path, replace=True, what="dataset store", error=StoreError) as staging:
        build_layout(staging, config)
    return _writable(where)


def _create_in_object_store(where: Location, config: Config) -> zarr.Group:
    """The dataset store at ``where`` in an object store, created where there is none.

    An object store has no rename: the layout is built in a temporary directory and uploaded, the root
    ``zarr.json`` last by a conditional create (``If-None-Match: *``), so the store exists for every reader only
    once whole, and of two processes creating it at once one makes it and the other reopens it. Each chunk's
    rows and its completion mark are then objects of their own (one per chunk: workers never write the same
    object), the mark written last (:func:`write_chunk`).
    """
    from mpi_lidar.storage.objects import exists, upload_files, write_object

    if not exists(where.joinpath("zarr.json")):
        with tempfile.TemporaryDirectory(prefix="mpi-lidar-dataset-") as temporary:
            staging = Path(temporary) / "layout.zarr"
            build_layout(staging, config)
            upload_files(staging, where, skip=("zarr.json",))
            with suppress(FileExistsError):  # made by another process meanwhile: reopened and checked below
                write_object(where.joinpath("zarr.json"), (staging / "zarr.json").read_bytes(), create=True)
    group = open_store(where.url)
    _check_same_config(where.url, group, config)
    return _writable(where)


def _writable(where: Location) -> zarr.Group:
    """The dataset store at ``where`` opened to write chunks into: as Zarr v3, as it was built, so that zarr
    never probes for Zarr v2 metadata (three requests more in an object store, once per chunk written)."""
    return zarr.open_group(store=zarr_store(where, read_only=False), mode="r+", use_consolidated=False, zarr_format=3)


def _check_free_space(path: Path, config: Config) -> None:
    """Refuse a store the disk cannot hold, before creating anything (uncompressed size: noise barely compresses)."""
    row_bytes = 2 * len(config.frequencies_hz) * 4 + 8 + len(THETA_NAMES) * 8 + 1
    needed = config.dataset.samples * row_bytes
    existing = next((p for p in (path, *path.parents) if p.exists()), Path("."))
    free = shutil.disk_usage(existing).free
    if needed > free:
        raise StoreError(f"dataset store {path} needs about {needed / 2**30:.1f} GiB for {config.dataset.samples:,} "
                         f"rows and {existing} has {free / 2**30:.1f} GiB free; lower samples or choose another --out")


def _is_empty_dir(path: Path) -> bool:
    return path.is_dir() and not any(path.iterdir())


def _check_same_config(path: str | Path, group: zarr.Group, config: Config) -> None:
    found = group.attrs.get("config_sha256")
    if found != config_sha256(config):
        raise StoreError(
            f"dataset store {path} was written by another configuration (sha256 {str(found)[:12]}, this one "
            f"{config_sha256(config)[:12]}); refusing to mix them: choose another --out or delete the store"
        )


def open_store(path: str | Path, mode: Literal["r", "r+"] = "r") -> zarr.Group:
    """Open a dataset store (a path or an object-store URL) after checking its schema and arrays;
    :class:`StoreError` on anything else."""
    return open_checked(path, mode)[0]


def open_checked(path: str | Path, mode: Literal["r", "r+"] = "r") -> tuple[zarr.Group, dict[str, zarr.Array]]:
    """:func:`open_store`'s group, with its six arrays by name as the checks opened them, once each (every
    ``group[name]`` reads an array's metadata again: a request in an object store)."""
    where = location(path)
    shown = where.url if not where.is_local else path
    # Links, FIFOs and devices inside the store, and oversized metadata, are refused before zarr opens a file.
    files = _store_files(where, shown)
    try:
        group = zarr.open_group(store=zarr_store(where, read_only=mode == "r"), mode=mode, use_consolidated=False,
                                zarr_format=None if where.is_local else 3)
        attrs = dict(group.attrs)
    except Exception as exc:  # zarr raises several types for foreign or broken metadata
        raise StoreError(f"{shown} is not a readable Zarr store ({type(exc).__name__}: {exc})") from None
    if attrs.get("schema") != SCHEMA:
        raise StoreError(f"{shown} is not an mpi-lidar dataset (schema {attrs.get('schema')!r}, "
                         f"expected {SCHEMA!r})")
    arrays = check_layout(shown, group, attrs)
    check_chunk_files(shown, files, arrays)
    return group, arrays


def _store_files(where: Location, shown: str | Path) -> dict[str, int]:
    """Every file (object) of a store with its size, links and oversized metadata refused (one listing in an
    object store); a store that is not there is refused with one line."""
    if where.is_local:
        path = where.local_path()
        if not path.exists():
            raise StoreError(f"dataset store {path} does not exist; create it with "
                             f"'mpi-lidar simulate --out {path}'")
        return check_store_files(path) if path.is_dir() else {}
    from mpi_lidar.storage.objects import list_files

    files = list_files(where)
    if "zarr.json" not in files:
        raise StoreError(f"dataset store {shown} does not exist; create it with 'mpi-lidar simulate --out {shown}'")
    return files


def store_config(group: zarr.Group) -> Config:
    return config_from_json(json.dumps(group.attrs["config"]))


def completed_chunks(group: zarr.Group, arrays: Mapping[str, zarr.Array] | None = None) -> NDArray[np.bool_]:
    """Which chunks are complete; ``arrays``: the store's arrays as :func:`open_checked` opened them, if at hand."""
    return _read_whole(group, "chunk_done", arrays).astype(bool)


def _read_whole(group: zarr.Group, name: str, arrays: Mapping[str, zarr.Array] | None = None) -> NDArray:
    """A small bookkeeping array (taken from ``arrays`` where given, not opened again), read at once; damage to
    it is one :class:`IntegrityError` naming it."""
    array = arrays[name] if arrays is not None else store_array(group, name)
    return read_chunk(array, (slice(None),) * array.ndim, str(getattr(group.store, "root", group.store)), name, "(any)")


def incomplete_chunks(group: zarr.Group) -> list[int]:
    return [int(i) for i in np.flatnonzero(~completed_chunks(group))]


def store_key(config: Config, version: str = __version__) -> str:
    """A directory name for the store of this configuration made by this package version."""
    return hashlib.sha256((config_sha256(config) + version).encode()).hexdigest()[:16]


def is_complete(path: str | Path) -> bool:
    return bool(completed_chunks(open_store(path)).all())


def chunk_fingerprints(group: zarr.Group, arrays: Mapping[str, zarr.Array] | None = None) -> NDArray[np.uint8]:
    """The fingerprints (chunks, arrays, 32) recorded by :func:`write_chunk` (every dataset has them:
    :func:`open_store` refuses one without); ``arrays`` as for :func:`completed_chunks`."""
    return _read_whole(group, "chunk_sha256", arrays)


def write_chunk(path: str | Path, config: Config, index: int) -> bool:
    """Simulate chunk ``index`` into its row range of the store; skip it if already complete.

    Returns True when the chunk was written, False when it was already complete. The completion mark is
    written after the data, so a chunk interrupted part-way is redone on the next run.
    """
    group = _writable(location(path))
    if store_array(group, "chunk_done")[index]:
        return False
    chunk = simulate_chunk(config, index)
    rows = SamplingPlan.from_config(config).rows(index)
    store_array(group, "features")[rows] = chunk.features
    store_array(group, "target")[rows] = chunk.target
    store_array(group, "theta")[rows] = chunk.theta
    store_array(group, "split")[rows] = chunk.split
    store_array(group, "chunk_sha256")[index] = np.stack([
        np.frombuffer(fingerprint(np.asarray(getattr(chunk, name), dtype=store_array(group, name).dtype)),
                      dtype=np.uint8)
        for name in DATA_ARRAYS])
    store_array(group, "chunk_done")[index] = 1
    return True
