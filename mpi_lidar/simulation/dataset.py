"""Labelled datasets: chunked sampling, simulation and the Zarr store layout.

A dataset is generated chunk by chunk. Chunk i draws its rows from a generator seeded by (seed, i), so
the bytes of a chunk never depend on which process writes it or in which order. Each chunk writes its own
row range of every array, then marks itself complete in ``chunk_done``: a chunk whose mark is set is
complete, and a re-run skips it. The loop over the chunks is :func:`mpi_lidar.workflows.generate.generate`.

Layout (Zarr v3, one group): ``features`` float32 (n, 2F) = [depth per frequency, amplitude per frequency];
``target`` float64 (n,) true d_AS [m]; ``theta`` float64 (n, 6) scene parameters; ``split`` uint8 (n,)
0 = train, 1 = test; ``chunk_done`` uint8 (chunks,). Root attributes carry the schema, frequencies,
feature and theta names, the configuration and its SHA-256, and the package version.
"""

from __future__ import annotations

import hashlib
import json
import shutil
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path
from typing import TYPE_CHECKING, Any, Literal, cast

import numpy as np
import zarr
from numpy.typing import NDArray
from zarr.codecs import BloscCodec

from mpi_lidar import __version__
from mpi_lidar.config import (
    MAX_CHUNK_ROWS,
    MAX_CHUNKS,
    MAX_SAMPLES,
    Config,
    config_from_json,
    config_json,
    config_sha256,
)
from mpi_lidar.errors import StoreError
from mpi_lidar.physics import SensorModel, make_sensor
from mpi_lidar.physics.demod import unambiguous_range
from mpi_lidar.physics.noise import unwrapped_rows
from mpi_lidar.scans.store import consolidate
from mpi_lidar.simulation.sampling import THETA_NAMES, sample_theta
from mpi_lidar.storage.atomic import atomic_path
from mpi_lidar.storage.integrity import (
    FINGERPRINT_BYTES,
    check_chunk_files,
    check_fingerprint,
    check_store_files,
    fingerprint,
    read_chunk,
)
from mpi_lidar.storage.variables import DATASET

if TYPE_CHECKING:
    import dask.array as da

SCHEMA = "mpi-lidar/dataset@1"
SPLIT_CODES = {"train": 0, "test": 1}
DATA_ARRAYS = ("features", "target", "theta", "split")
# What xarray shows of each array (CF ``units`` and ``long_name``), as the store-variable registry declares it;
# the columns are named in ``columns``.
ARRAY_DESCRIPTIONS = {name: {"units": DATASET[name].units, "long_name": DATASET[name].long_name}
                      for name in DATA_ARRAYS}
ARRAYS = (*DATA_ARRAYS, "chunk_done", "chunk_sha256")
# Stream of the seed tree reserved for summary statistics, apart from the chunk streams (seed, i).
SUMMARY_STREAM = (1, 0)


def frequency_labels(frequencies_hz: tuple[float, ...]) -> list[str]:
    return [f"{f / 1e6:g}MHz" for f in frequencies_hz]


def raw_feature_names(frequencies_hz: tuple[float, ...]) -> list[str]:
    """depth_<f>MHz then amplitude_<f>MHz, in frequency order (the dataset's ``features`` columns)."""
    labels = frequency_labels(frequencies_hz)
    return [f"depth_{x}" for x in labels] + [f"amplitude_{x}" for x in labels]


@dataclass(frozen=True)
class SamplingPlan:
    """n rows in chunks of ``chunk_rows`` (the last one shorter), drawn from ``seed``."""

    samples: int
    chunk_rows: int
    seed: int

    @classmethod
    def from_config(cls, config: Config) -> SamplingPlan:
        d = config.dataset
        return cls(d.samples, d.chunk_rows, d.seed)

    @property
    def chunks(self) -> int:
        return -(-self.samples // self.chunk_rows)

    def rows_in(self, indices: list[int]) -> int:
        """How many rows the given chunks hold."""
        return sum(self.rows(i).stop - self.rows(i).start for i in indices)

    def rows(self, index: int) -> slice:
        if not 0 <= index < self.chunks:
            raise IndexError(f"chunk {index} outside 0..{self.chunks - 1}")
        return slice(index * self.chunk_rows, min((index + 1) * self.chunk_rows, self.samples))


@dataclass(frozen=True)
class Chunk:
    features: NDArray[np.float32]
    target: NDArray[np.float64]
    theta: NDArray[np.float64]
    split: NDArray[np.uint8]


def seeded_rng(seed: int, *stream: int) -> np.random.Generator:
    """A generator for one stream of the seed tree: chunk i uses stream (i,)."""
    return np.random.default_rng(np.random.SeedSequence(seed, spawn_key=stream))


@lru_cache(maxsize=8)
def cached_sensor(config: Config) -> SensorModel:
    return make_sensor(config)


def simulate_rows(config: Config, n: int, rng: np.random.Generator) -> tuple[NDArray[np.float32], NDArray[np.float64]]:
    """n rows drawn from the configured prior and measured by its sensor, from ``rng``: the features (n, 2F)
    (depths then amplitudes, float32) and theta (n, 6); the true depth d_AS is theta's first column. [m, V^2]

    Where the prior reaches ranges at which a frequency's depth wraps (:func:`prior_wraps`), the depths are
    unwrapped into one range as correction unwraps a scan's (:func:`mpi_lidar.physics.noise.unwrapped_rows`),
    so the model learns from what it will be given.
    """
    theta = sample_theta(config.prior, n, rng)
    depth, amplitude = cached_sensor(config).measure(theta, rng)
    rows = np.concatenate([depth, amplitude], axis=1).astype(np.float32)
    if prior_wraps(config):
        rows, _ = unwrapped_rows(rows, config.frequencies_hz, config.sensor)
    return rows, theta


# Share of the highest frequency's unambiguous range that a prior's longest path may reach and still count as
# never wrapping: a margin for the noise of the farthest, weakest rows.
NO_WRAP_SHARE = 0.9


def prior_wraps(config: Config) -> bool:
    """Whether the prior's longest path (farthest d_AS plus longest d_AB) reaches 90 % of the smallest
    unambiguous range c / 2f: only then can a measured depth wrap. A prior that cannot wrap is not unwrapped,
    so its datasets stay byte for byte what they were before unwrapping existed. [1]"""
    longest_m = config.prior.d_as_m[1] + config.prior.d_ab_m[1]
    shortest_range_m = float(unambiguous_range(max(config.frequencies_hz), config.sensor.speed_of_light_m_per_s))
    return longest_m >= NO_WRAP_SHARE * shortest_range_m


def simulate_chunk(config: Config, index: int) -> Chunk:
    """Draw, simulate and split chunk ``index`` of the configured plan; a pure function of both."""
    plan = SamplingPlan.from_config(config)
    rows = plan.rows(index)
    n = rows.stop - rows.start
    rng = seeded_rng(plan.seed, index)
    features, theta = simulate_rows(config, n, rng)
    split = np.zeros(n, dtype=np.uint8)
    split[rng.permutation(n)[: round(n * config.dataset.test_fraction)]] = SPLIT_CODES["test"]
    return Chunk(features=features, target=theta[:, 0].copy(), theta=theta, split=split)


# --- the store ----------------------------------------------------------------------------------------


def _root_attributes(config: Config) -> dict[str, Any]:
    return {
        "schema": SCHEMA,
        "frequencies_hz": list(config.frequencies_hz),
        "feature_names": raw_feature_names(config.frequencies_hz),
        "theta_names": list(THETA_NAMES),
        "split_codes": SPLIT_CODES,
        "config": json.loads(config_json(config)),
        "config_sha256": config_sha256(config),
        "package_version": __version__,
        "samples": config.dataset.samples,
        "chunk_rows": config.dataset.chunk_rows,
    }


def _build_layout(path: Path, config: Config) -> None:
    plan = SamplingPlan.from_config(config)
    n, rows, width = plan.samples, plan.chunk_rows, 2 * len(config.frequencies_hz)
    compressors = [BloscCodec(cname="zstd", clevel=3, shuffle="shuffle")]
    group = zarr.open_group(store=str(path), mode="w-")
    shapes = {"features": (n, width), "target": (n,), "theta": (n, len(THETA_NAMES)), "split": (n,)}
    for name, shape in shapes.items():
        declared = DATASET[name]
        group.create_array(name, shape=shape, chunks=(rows, *shape[1:]), dtype=declared.dtype,
                           compressors=compressors, fill_value=0, dimension_names=declared.dims)
    group["features"].attrs["columns"] = raw_feature_names(config.frequencies_hz)
    group["theta"].attrs["columns"] = list(THETA_NAMES)
    for name, described in ARRAY_DESCRIPTIONS.items():
        group[name].attrs.update(described)
    group["split"].attrs.update({"flag_values": list(SPLIT_CODES.values()), "flag_meanings": " ".join(SPLIT_CODES)})
    group.create_array("chunk_done", shape=(plan.chunks,), chunks=(1,), dtype=DATASET["chunk_done"].dtype,
                       fill_value=0, dimension_names=DATASET["chunk_done"].dims)
    # One row of fingerprints per chunk, written with its completion mark (mpi_lidar.storage.integrity).
    group.create_array("chunk_sha256", shape=(plan.chunks, len(DATA_ARRAYS), FINGERPRINT_BYTES),
                       chunks=(1, len(DATA_ARRAYS), FINGERPRINT_BYTES), dtype=DATASET["chunk_sha256"].dtype,
                       fill_value=0, dimension_names=DATASET["chunk_sha256"].dims)
    group.attrs.update(_root_attributes(config))
    consolidate(path)  # for xarray; this package's readers read each array's own metadata


def create_store(path: str | Path, config: Config) -> zarr.Group:
    """Create an empty dataset store for ``config``, or reopen the one already there for the same config.

    The layout is built under a temporary name beside ``path`` and renamed into place, so a crash never
    leaves a half-made store. A store made from another configuration, or anything at ``path`` that is
    not a dataset store (other than an empty directory), is refused with :class:`StoreError`.
    """
    path = Path(path)
    if path.exists() and not _is_empty_dir(path):
        group = open_store(path)
        _check_same_config(path, group, config)
        return zarr.open_group(store=str(path), mode="r+", use_consolidated=False)
    _check_free_space(path, config)
    # Here path is absent or an empty directory, which the new store may replace.
    with atomic_path(path, replace=True, what="dataset store", error=StoreError) as staging:
        _build_layout(staging, config)
    return zarr.open_group(store=str(path), mode="r+", use_consolidated=False)


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


def _check_same_config(path: Path, group: zarr.Group, config: Config) -> None:
    found = group.attrs.get("config_sha256")
    if found != config_sha256(config):
        raise StoreError(
            f"dataset store {path} was written by another configuration (sha256 {str(found)[:12]}, this one "
            f"{config_sha256(config)[:12]}); refusing to mix them: choose another --out or delete the store"
        )


def open_store(path: str | Path, mode: Literal["r", "r+"] = "r") -> zarr.Group:
    """Open a dataset store after checking its schema and arrays; :class:`StoreError` on anything else."""
    path = Path(path)
    if not path.exists():
        raise StoreError(f"dataset store {path} does not exist; create it with 'mpi-lidar simulate --out {path}'")
    # Links, FIFOs and devices inside the store, and oversized metadata, are refused before zarr opens a file.
    files = check_store_files(path) if path.is_dir() else {}
    try:
        group = zarr.open_group(store=str(path), mode=mode, use_consolidated=False)
        attrs = dict(group.attrs)
    except Exception as exc:  # zarr raises several types for foreign or broken metadata
        raise StoreError(f"{path} is not a readable Zarr store ({type(exc).__name__}: {exc})") from None
    if attrs.get("schema") != SCHEMA:
        raise StoreError(f"{path} is not an mpi-lidar dataset (schema {attrs.get('schema')!r}, "
                         f"expected {SCHEMA!r})")
    _check_layout(path, group, attrs)
    check_chunk_files(path, files, {name: _array(group, name) for name in ARRAYS})
    return group


def _check_layout(path: Path, group: zarr.Group, attrs: Mapping[str, Any]) -> None:
    """Every array (the fingerprints ``chunk_sha256`` included: every dataset of this schema has them) of the
    shape, dtype and row chunks the attributes give, which are within the configuration's bounds; checked from
    the metadata alone, before anything is read or allocated."""
    try:
        n, width, chunk_rows = int(attrs["samples"]), 2 * len(attrs["frequencies_hz"]), int(attrs["chunk_rows"])
        if not (1 <= n <= MAX_SAMPLES and 1 <= chunk_rows <= MAX_CHUNK_ROWS and -(-n // chunk_rows) <= MAX_CHUNKS):
            raise StoreError(f"dataset {path} declares {n:,} samples in chunks of {chunk_rows:,} rows, beyond what "
                             "a dataset may hold; the store is damaged: regenerate it")
        chunks = -(-n // chunk_rows)
        expected = {
            "features": ((n, width), np.float32, chunk_rows), "target": ((n,), np.float64, chunk_rows),
            "theta": ((n, len(THETA_NAMES)), np.float64, chunk_rows), "split": ((n,), np.uint8, chunk_rows),
            "chunk_done": ((chunks,), np.uint8, 1),
            "chunk_sha256": ((chunks, len(DATA_ARRAYS), FINGERPRINT_BYTES), np.uint8, 1),
        }
        for name, (shape, dtype, rows) in expected.items():
            array = _array(group, name)
            if array.shape != shape or array.dtype != dtype or array.shards or tuple(array.chunks) != (
                    min(rows, shape[0]), *shape[1:]):
                raise StoreError(f"dataset {path}: array {name!r} is {array.dtype}{array.shape} in chunks of "
                                 f"{array.chunks}, expected {np.dtype(dtype)}{shape} in chunks of "
                                 f"{(min(rows, shape[0]), *shape[1:])}; the store is damaged: regenerate it")
    except KeyError as exc:
        raise StoreError(f"dataset {path} lacks {exc}; the store is truncated: regenerate it") from None
    except (TypeError, ValueError) as exc:
        raise StoreError(f"dataset {path} has malformed attributes ({type(exc).__name__}: {exc}); "
                         "the store is damaged: regenerate it") from None


def _array(group: zarr.Group, name: str) -> zarr.Array:
    """The array ``name`` of a dataset store (:func:`open_store` checked that each is an array of its shape)."""
    return cast(zarr.Array, group[name])


def store_config(group: zarr.Group) -> Config:
    return config_from_json(json.dumps(group.attrs["config"]))


def completed_chunks(group: zarr.Group) -> NDArray[np.bool_]:
    return _read_whole(group, "chunk_done").astype(bool)


def _read_whole(group: zarr.Group, name: str) -> NDArray:
    """A small bookkeeping array, read at once; damage to it is one :class:`IntegrityError` naming it."""
    array = _array(group, name)
    return read_chunk(array, (slice(None),) * array.ndim, str(getattr(group.store, "root", group.store)), name, "(any)")


def incomplete_chunks(group: zarr.Group) -> list[int]:
    return [int(i) for i in np.flatnonzero(~completed_chunks(group))]


def store_key(config: Config, version: str = __version__) -> str:
    """A directory name for the store of this configuration made by this package version."""
    return hashlib.sha256((config_sha256(config) + version).encode()).hexdigest()[:16]


def is_complete(path: str | Path) -> bool:
    return bool(completed_chunks(open_store(path)).all())


def write_chunk(path: str | Path, config: Config, index: int) -> bool:
    """Simulate chunk ``index`` into its row range of the store; skip it if already complete.

    Returns True when the chunk was written, False when it was already complete. The completion mark is
    written after the data, so a chunk interrupted part-way is redone on the next run.
    """
    group = zarr.open_group(store=str(path), mode="r+", use_consolidated=False)
    if _array(group, "chunk_done")[index]:
        return False
    chunk = simulate_chunk(config, index)
    rows = SamplingPlan.from_config(config).rows(index)
    _array(group, "features")[rows] = chunk.features
    _array(group, "target")[rows] = chunk.target
    _array(group, "theta")[rows] = chunk.theta
    _array(group, "split")[rows] = chunk.split
    _array(group, "chunk_sha256")[index] = np.stack([
        np.frombuffer(fingerprint(np.asarray(getattr(chunk, name), dtype=_array(group, name).dtype)), dtype=np.uint8)
        for name in DATA_ARRAYS])
    _array(group, "chunk_done")[index] = 1
    return True


# --- readers ----------------------------------------------------------------------------------------------


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
    group = open_store(path)
    try:
        return _info(path, group)
    except (KeyError, TypeError, ValueError, RuntimeError) as exc:  # codecs raise RuntimeError on bad chunks
        reason = str(exc).splitlines()[0] if str(exc) else ""
        raise StoreError(f"dataset {path} has damaged metadata or chunk marks ({type(exc).__name__}: {reason}); "
                         "regenerate it") from None


def _info(path: str | Path, group: zarr.Group) -> DatasetInfo:
    done = completed_chunks(group)
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


def _complete_info(path: str | Path) -> DatasetInfo:
    info = dataset_info(path)
    if not info.complete:
        raise StoreError(f"dataset {path} is incomplete ({info.chunks_done} of {info.chunks} chunks); "
                         f"finish it with 'mpi-lidar simulate --out {path}' and the same configuration")
    return info


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
    info = _complete_info(path)
    group = open_store(path)
    fingerprints = chunk_fingerprints(group)
    arrays = {name: _verified_lazy(path, _array(group, name), k, fingerprints) for k, name in enumerate(DATA_ARRAYS)}
    return LazyDataset(info=info, **arrays)


def chunk_fingerprints(group: zarr.Group) -> NDArray[np.uint8]:
    """The fingerprints (chunks, arrays, 32) recorded by :func:`write_chunk` (every dataset has them:
    :func:`open_store` refuses one without)."""
    return _read_whole(group, "chunk_sha256")


def _verified_lazy(path: str | Path, array: zarr.Array, k: int, fingerprints: NDArray | None) -> da.Array:
    """A dask array whose every block is read and checked against its fingerprint where it is computed."""
    import dask.array as da  # only where a dask array is built: the rest of the module stays light

    chunks = da.core.normalize_chunks(array.chunks, array.shape)
    return da.map_blocks(_load_verified_block, dtype=array.dtype, chunks=chunks, path=str(path),
                         array_name=array.basename, k=k, fingerprints=fingerprints,
                         meta=np.empty((0,) * array.ndim, dtype=array.dtype))


def _load_verified_block(path: str, array_name: str, k: int, fingerprints: NDArray | None, block_info=None) -> NDArray:
    info = block_info[None]
    where = tuple(slice(start, stop) for start, stop in info["array-location"])
    index = info["chunk-location"][0]
    group = zarr.open_group(store=path, mode="r", use_consolidated=False)
    values = read_chunk(_array(group, array_name), where, path, array_name, index)
    if fingerprints is not None:
        check_fingerprint(values, fingerprints[index, k], path, array_name, index)
    return values


def read_verified_chunk(path: str | Path, group: zarr.Group, index: int, fingerprints: NDArray | None,
                        names: tuple[str, ...] = DATA_ARRAYS) -> dict[str, NDArray]:
    """The rows of chunk ``index`` of the named arrays, each checked against its fingerprint."""
    chunk_rows = _array(group, "target").chunks[0]
    rows = slice(index * chunk_rows, (index + 1) * chunk_rows)
    out = {}
    for name in names:
        array = _array(group, name)
        where = (rows,) + (slice(None),) * (array.ndim - 1)
        values = read_chunk(array, where, str(path), name, index)
        if fingerprints is not None:
            check_fingerprint(values, fingerprints[index, DATA_ARRAYS.index(name)], str(path), name, index)
        out[name] = values
    return out


def read_verified(path: str | Path, names: tuple[str, ...] = DATA_ARRAYS,
                  on_chunk: Callable[[dict[str, NDArray]], dict[str, NDArray]] | None = None) -> dict[str, NDArray]:
    """Whole arrays of a store, streamed chunk by chunk and each chunk verified; ``on_chunk`` may reduce a chunk."""
    group = open_store(path)
    fingerprints = chunk_fingerprints(group)
    done = completed_chunks(group)
    if not done.all():  # an unfinished chunk has no fingerprint: its rows would be read as fill values
        raise StoreError(f"dataset {path} is incomplete ({int(done.sum())} of {done.size} chunks); finish it with "
                         f"'mpi-lidar simulate --out {path}' and the same configuration")
    parts: dict[str, list[NDArray]] = {name: [] for name in names}
    for index in range(done.size):
        chunk = read_verified_chunk(path, group, index, fingerprints, names)
        if on_chunk is not None:
            chunk = on_chunk(chunk)
        for name in names:
            parts[name].append(chunk[name])
    return {name: np.concatenate(parts[name]) for name in names}


def verify_dataset(path: str | Path) -> int:
    """Check every chunk of a complete dataset store against its fingerprint; the number of chunks checked."""
    info = _complete_info(path)
    read_verified(path, on_chunk=lambda chunk: {name: values[:0] for name, values in chunk.items()})
    return info.chunks


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
    info = _complete_info(path)
    if split not in (*SPLIT_CODES, "all"):
        raise StoreError(f"unknown split {split!r}; choose train, test or all")
    split_codes = read_verified(path, ("split",))["split"]
    rows = np.arange(info.samples) if split == "all" else np.flatnonzero(split_codes == SPLIT_CODES[split])
    if max_rows is not None and max_rows < rows.size:
        rows = np.sort(np.random.default_rng(seed).choice(rows, size=max_rows, replace=False))
    if rows.size == 0:
        raise StoreError(f"dataset {path} has no {split} rows")
    arrays = _rows_verified(path, rows, ("features", "target", "theta"))
    return Subsample(info=info, rows=rows, **arrays)


def _rows_verified(path: str | Path, rows: NDArray[np.int64], names: tuple[str, ...]) -> dict[str, NDArray]:
    """The given sorted rows of the named arrays, read chunk by chunk, every chunk touched verified."""
    group = open_store(path)
    fingerprints = chunk_fingerprints(group)
    chunk_rows = _array(group, "target").chunks[0]
    parts: dict[str, list[NDArray]] = {name: [] for name in names}
    for index in np.unique(rows // chunk_rows):
        chunk = read_verified_chunk(path, group, int(index), fingerprints, names)
        local = rows[(rows // chunk_rows) == index] - index * chunk_rows
        for name in names:
            parts[name].append(chunk[name][local])
    return {name: np.concatenate(parts[name]) for name in names}


# --- summary --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class DatasetSummary:
    """Raw depth errors of a dataset, per frequency. Errors in metres."""

    path: str
    samples: int
    train: int
    test: int
    frequencies_hz: tuple[float, ...]
    mae_m: tuple[float, ...]
    rmse_m: tuple[float, ...]
    noise_only_mae_m: tuple[float, ...]
    noise_only_rows: int
    config_sha256: str

    def to_markdown(self) -> str:
        lines = [
            f"Dataset `{self.path}`: {self.samples:,} rows ({self.train:,} train, {self.test:,} test), "
            f"config {self.config_sha256[:12]}",
            "",
            "| frequency | raw MAE [mm] | raw RMSE [mm] | noise-only MAE [mm] |",
            "|---|---|---|---|",
        ]
        for f, mae, rmse, noise in zip(self.frequencies_hz, self.mae_m, self.rmse_m, self.noise_only_mae_m,
                                       strict=True):
            lines.append(f"| {f / 1e6:g} MHz | {mae * 1e3:.3f} | {rmse * 1e3:.3f} | {noise * 1e3:.3f} |")
        lines += ["", f"Noise-only: the same scenes without the A -> B -> A path, first {self.noise_only_rows:,} rows."]
        return "\n".join(lines)


def summarize(path: str | Path, noise_only_rows: int = 200_000) -> DatasetSummary:
    """Raw MAE and RMSE of each frequency's depth against the truth, and the noise-only MAE.

    The noise-only MAE simulates the first ``noise_only_rows`` scenes again without multipath, from a
    stream of the seed tree reserved for it, so it is reproducible and independent of the stored noise.
    """
    group = open_store(path)
    config = store_config(group)
    n_freq = len(config.frequencies_hz)
    stored = read_verified(path)
    error = stored["features"][:, :n_freq].astype(np.float64) - stored["target"][:, None]
    split = stored["split"]
    rows = min(noise_only_rows, config.dataset.samples)
    theta = stored["theta"][:rows]
    clean_depth, clean_amplitude = cached_sensor(config).measure(
        theta, seeded_rng(config.dataset.seed, *SUMMARY_STREAM), multipath=False)
    if prior_wraps(config):  # as the stored rows are
        clean = np.concatenate([clean_depth, clean_amplitude], axis=1).astype(np.float32)
        clean_depth = unwrapped_rows(clean, config.frequencies_hz, config.sensor)[0][:, :n_freq].astype(np.float64)
    noise_error = clean_depth - theta[:, :1]
    return DatasetSummary(
        path=str(path),
        samples=config.dataset.samples,
        train=int((split == SPLIT_CODES["train"]).sum()),
        test=int((split == SPLIT_CODES["test"]).sum()),
        frequencies_hz=config.frequencies_hz,
        mae_m=tuple(np.abs(error).mean(0).tolist()),
        rmse_m=tuple(np.sqrt((error**2).mean(0)).tolist()),
        noise_only_mae_m=tuple(np.abs(noise_error).mean(0).tolist()),
        noise_only_rows=rows,
        config_sha256=cast(str, group.attrs["config_sha256"]),
    )
