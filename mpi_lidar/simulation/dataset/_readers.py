"""Reading a complete dataset store: what it says about itself, and its rows verified against their fingerprints."""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any, Literal

import numpy as np
import zarr
from numpy.typing import NDArray

from mpi_lidar.config import Config
from mpi_lidar.errors import StoreError
from mpi_lidar.locations import location
from mpi_lidar.simulation.dataset._chunks import SPLIT_CODES
from mpi_lidar.simulation.dataset._layout import DATA_ARRAYS, store_arrays
from mpi_lidar.simulation.dataset._store import chunk_fingerprints, completed_chunks, open_checked, store_config
from mpi_lidar.storage.integrity import check_fingerprint, read_chunk
from mpi_lidar.storage.objects import zarr_store

if TYPE_CHECKING:
    import dask.array as da


@dataclass(frozen=True)
class DatasetInfo:
    """What a store says about itself."""

    path: str
    config: Config
    config_sha256: str
    frequencies_hz: tuple[float, ...]
    feature_names: tuple[str, ...]
    theta_names: tuple[str, ...]
    samples: int
    chunks_done: int
    chunks: int
    package_version: str

    @property
    def complete(self) -> bool:
        return self.chunks_done == self.chunks


def dataset_info(path: str | Path) -> DatasetInfo:
    return _described(path, *open_checked(path))


def _described(path: str | Path, group: zarr.Group, arrays: Mapping[str, zarr.Array]) -> DatasetInfo:
    """:func:`dataset_info` of a store already opened (and checked) by :func:`open_checked`, with its arrays."""
    try:
        return _info(path, group, arrays)
    except (KeyError, TypeError, ValueError, RuntimeError) as exc:  # codecs raise RuntimeError on bad chunks
        reason = str(exc).splitlines()[0] if str(exc) else ""
        raise StoreError(f"dataset {path} has damaged metadata or chunk marks ({type(exc).__name__}: {reason}); "
                         "regenerate it") from None


def _info(path: str | Path, group: zarr.Group, arrays: Mapping[str, zarr.Array]) -> DatasetInfo:
    done = completed_chunks(group, arrays)
    attrs: Mapping[str, Any] = group.attrs  # JSON whose layout open_store checked
    return DatasetInfo(
        path=str(path),
        config=store_config(group),
        config_sha256=attrs["config_sha256"],
        frequencies_hz=tuple(attrs["frequencies_hz"]),
        feature_names=tuple(attrs["feature_names"]),
        theta_names=tuple(attrs["theta_names"]),
        samples=int(attrs["samples"]),
        chunks_done=int(done.sum()),
        chunks=done.size,
        package_version=str(attrs["package_version"]),
    )


def _complete_info(path: str | Path, group: zarr.Group, arrays: Mapping[str, zarr.Array]) -> DatasetInfo:
    info = _described(path, group, arrays)
    if not info.complete:  # an unfinished chunk has no fingerprint: its rows would be read as fill values
        raise StoreError(f"dataset {path} is incomplete ({info.chunks_done} of {info.chunks} chunks); "
                         f"finish it with 'mpi-lidar simulate --out {path}' and the same configuration")
    return info


@dataclass(frozen=True)
class _ReadPass:
    """A complete store opened for one pass of reads: opened and checked once, each array's metadata read once,
    by the checks (every ``group[name]`` reads it again: a request per array and chunk in an object store)."""

    path: str
    info: DatasetInfo
    fingerprints: NDArray[np.uint8]
    arrays: Mapping[str, zarr.Array]

    @property
    def chunk_rows(self) -> int:
        return int(self.arrays["target"].chunks[0])

    def chunk(self, index: int, names: tuple[str, ...]) -> dict[str, NDArray]:
        """The rows of chunk ``index`` of the named arrays, each checked against its fingerprint."""
        return _verified_chunk(self.path, self.arrays, index, self.fingerprints, names)


def _open_complete(path: str | Path) -> _ReadPass:
    group, arrays = open_checked(path)
    info = _complete_info(path, group, arrays)
    return _ReadPass(str(path), info, chunk_fingerprints(group, arrays), {name: arrays[name] for name in DATA_ARRAYS})


@dataclass(frozen=True)
class LazyDataset:
    """Dask arrays over a complete store, chunked as stored; nothing is read until computed."""

    info: DatasetInfo
    features: da.Array
    target: da.Array
    theta: da.Array
    split: da.Array


def read_lazy(path: str | Path) -> LazyDataset:
    """Open a complete dataset as dask arrays (for training on a cluster)."""
    opened = _open_complete(path)
    arrays = {name: _verified_lazy(path, opened.arrays[name], k, opened.fingerprints)
              for k, name in enumerate(DATA_ARRAYS)}
    return LazyDataset(info=opened.info, **arrays)


def _verified_lazy(path: str | Path, array: zarr.Array, k: int, fingerprints: NDArray | None) -> da.Array:
    """A dask array whose every block is read and checked against its fingerprint where it is computed."""
    import dask.array as da  # only where a dask array is built: the rest of the module stays light

    chunks = da.core.normalize_chunks(array.chunks, array.shape)
    return da.map_blocks(_load_verified_block, dtype=array.dtype, chunks=chunks, path=str(path),
                         array_name=array.basename, zarr_format=array.metadata.zarr_format, k=k,
                         fingerprints=fingerprints, meta=np.empty((0,) * array.ndim, dtype=array.dtype))


def _load_verified_block(path: str, array_name: str, zarr_format: Literal[2, 3], k: int, fingerprints: NDArray | None,
                         block_info=None) -> NDArray:
    """One block, where it is computed (a Dask worker opens its own store): the array alone is opened, one read
    of its metadata, neither the group's nor another format's."""
    info = block_info[None]
    where = tuple(slice(start, stop) for start, stop in info["array-location"])
    index = info["chunk-location"][0]
    array = zarr.open_array(store=zarr_store(location(path)), path=array_name, mode="r", zarr_format=zarr_format)
    values = read_chunk(array, where, path, array_name, index)
    if fingerprints is not None:
        check_fingerprint(values, fingerprints[index, k], path, array_name, index)
    return values


def read_verified_chunk(path: str | Path, group: zarr.Group, index: int, fingerprints: NDArray | None,
                        names: tuple[str, ...] = DATA_ARRAYS) -> dict[str, NDArray]:
    """The rows of chunk ``index`` of the named arrays, each checked against its fingerprint."""
    arrays = store_arrays(group, tuple(dict.fromkeys(("target", *names))))  # target's chunks give the rows
    return _verified_chunk(str(path), arrays, index, fingerprints, names)


def _verified_chunk(path: str, arrays: Mapping[str, zarr.Array], index: int, fingerprints: NDArray | None,
                    names: tuple[str, ...]) -> dict[str, NDArray]:
    chunk_rows = arrays["target"].chunks[0]
    rows = slice(index * chunk_rows, (index + 1) * chunk_rows)
    out = {}
    for name in names:
        array = arrays[name]
        where = (rows,) + (slice(None),) * (array.ndim - 1)
        values = read_chunk(array, where, path, name, index)
        if fingerprints is not None:
            check_fingerprint(values, fingerprints[index, DATA_ARRAYS.index(name)], path, name, index)
        out[name] = values
    return out


def read_verified(path: str | Path, names: tuple[str, ...] = DATA_ARRAYS,
                  on_chunk: Callable[[dict[str, NDArray]], dict[str, NDArray]] | None = None) -> dict[str, NDArray]:
    """Whole arrays of a store, streamed chunk by chunk and each chunk verified; ``on_chunk`` may reduce a chunk."""
    return _read_all(_open_complete(path), names, on_chunk)


def _read_all(opened: _ReadPass, names: tuple[str, ...],
              on_chunk: Callable[[dict[str, NDArray]], dict[str, NDArray]] | None = None) -> dict[str, NDArray]:
    parts: dict[str, list[NDArray]] = {name: [] for name in names}
    for index in range(opened.info.chunks):
        chunk = opened.chunk(index, names)
        if on_chunk is not None:
            chunk = on_chunk(chunk)
        for name in names:
            parts[name].append(chunk[name])
    return {name: np.concatenate(parts[name]) for name in names}


def verify_dataset(path: str | Path) -> int:
    """Check every chunk of a complete dataset store against its fingerprint; the number of chunks checked."""
    opened = _open_complete(path)
    _read_all(opened, DATA_ARRAYS, on_chunk=lambda chunk: {name: values[:0] for name, values in chunk.items()})
    return opened.info.chunks


@dataclass(frozen=True)
class Subsample:
    """Rows of one split held in memory (for tuning), with their row numbers in the store."""

    info: DatasetInfo
    rows: NDArray[np.int64]
    features: NDArray[np.float32]
    target: NDArray[np.float64]
    theta: NDArray[np.float64]


def read_subsample(
    path: str | Path, split: str = "train", max_rows: int | None = None, seed: int = 0
) -> Subsample:
    """Read the rows of ``split`` ("train", "test" or "all"), or a seeded random ``max_rows`` of them."""
    opened = _open_complete(path)
    info = opened.info
    if split not in (*SPLIT_CODES, "all"):
        raise StoreError(f"unknown split {split!r}; choose train, test or all")
    split_codes = _read_all(opened, ("split",))["split"]
    rows = np.arange(info.samples) if split == "all" else np.flatnonzero(split_codes == SPLIT_CODES[split])
    if max_rows is not None and max_rows < rows.size:
        rows = np.sort(np.random.default_rng(seed).choice(rows, size=max_rows, replace=False))
    if rows.size == 0:
        raise StoreError(f"dataset {path} has no {split} rows")
    arrays = _rows_verified(opened, rows, ("features", "target", "theta"))
    return Subsample(info=info, rows=rows, **arrays)


def _rows_verified(opened: _ReadPass, rows: NDArray[np.int64], names: tuple[str, ...]) -> dict[str, NDArray]:
    """The given sorted rows of the named arrays, read chunk by chunk, every chunk touched verified."""
    chunk_rows = opened.chunk_rows
    parts: dict[str, list[NDArray]] = {name: [] for name in names}
    for index in np.unique(rows // chunk_rows):
        chunk = opened.chunk(int(index), names)
        local = rows[(rows // chunk_rows) == index] - index * chunk_rows
        for name in names:
            parts[name].append(chunk[name][local])
    return {name: np.concatenate(parts[name]) for name in names}
