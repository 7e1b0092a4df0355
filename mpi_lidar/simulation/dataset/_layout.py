"""The store's layout: its schema, arrays and attributes, built for a configuration and checked from metadata."""

from __future__ import annotations

import json
from collections.abc import Mapping
from pathlib import Path
from typing import Any, cast

import numpy as np
import zarr
from zarr.codecs import BloscCodec

from mpi_lidar import __version__
from mpi_lidar.config import MAX_CHUNK_ROWS, MAX_CHUNKS, MAX_SAMPLES, Config, config_json, config_sha256
from mpi_lidar.errors import StoreError
from mpi_lidar.scans.store import consolidate
from mpi_lidar.simulation.dataset._chunks import SPLIT_CODES, SamplingPlan
from mpi_lidar.simulation.sampling import THETA_NAMES
from mpi_lidar.storage.integrity import FINGERPRINT_BYTES
from mpi_lidar.storage.variables import DATASET

SCHEMA = "mpi-lidar/dataset@1"
DATA_ARRAYS = ("features", "target", "theta", "split")
# What xarray shows of each array (CF ``units`` and ``long_name``), as the store-variable registry declares it;
# the columns are named in ``columns``.
ARRAY_DESCRIPTIONS = {name: {"units": DATASET[name].units, "long_name": DATASET[name].long_name}
                      for name in DATA_ARRAYS}
ARRAYS = (*DATA_ARRAYS, "chunk_done", "chunk_sha256")


def frequency_labels(frequencies_hz: tuple[float, ...]) -> list[str]:
    return [f"{f / 1e6:g}MHz" for f in frequencies_hz]


def raw_feature_names(frequencies_hz: tuple[float, ...]) -> list[str]:
    """depth_<f>MHz then amplitude_<f>MHz, in frequency order (the dataset's ``features`` columns)."""
    labels = frequency_labels(frequencies_hz)
    return [f"depth_{x}" for x in labels] + [f"amplitude_{x}" for x in labels]


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


def build_layout(path: Path, config: Config) -> None:
    plan = SamplingPlan.from_config(config)
    n, rows, width = plan.samples, plan.chunk_rows, 2 * len(config.frequencies_hz)
    compressors = [BloscCodec(cname="zstd", clevel=3, shuffle="shuffle")]
    group = zarr.open_group(store=str(path), mode="w-", zarr_format=3)  # v3 whatever zarr's default is set to
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


def check_layout(path: str | Path, group: zarr.Group, attrs: Mapping[str, Any]) -> dict[str, zarr.Array]:
    """Every array (the fingerprints ``chunk_sha256`` included: every dataset of this schema has them) of the
    shape, dtype and row chunks the attributes give, which are within the configuration's bounds; checked from
    the metadata alone, before anything is read or allocated.

    Returns the arrays of :data:`ARRAYS` by name, each opened once here, for the checks and reads that follow
    (opening one again reads its metadata again: a request in an object store).
    """
    opened: dict[str, zarr.Array] = {}
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
            array = opened[name] = store_array(group, name)
            if array.shape != shape or array.dtype != dtype or array.shards or tuple(array.chunks) != (
                    min(rows, shape[0]), *shape[1:]):
                raise StoreError(f"dataset {path}: array {name!r} is {array.dtype}{array.shape} in chunks of "
                                 f"{array.chunks}, expected {np.dtype(dtype)}{shape} in chunks of "
                                 f"{(min(rows, shape[0]), *shape[1:])}; the store is damaged: regenerate it")
        return opened
    except KeyError as exc:
        raise StoreError(f"dataset {path} lacks {exc}; the store is truncated: regenerate it") from None
    except (TypeError, ValueError) as exc:
        raise StoreError(f"dataset {path} has malformed attributes ({type(exc).__name__}: {exc}); "
                         "the store is damaged: regenerate it") from None


def store_array(group: zarr.Group, name: str) -> zarr.Array:
    """The array ``name`` of a dataset store (:func:`open_store` checked that each is an array of its shape)."""
    return cast(zarr.Array, group[name])


def store_arrays(group: zarr.Group, names: tuple[str, ...]) -> dict[str, zarr.Array]:
    """The named arrays of a dataset store, each opened once: every ``group[name]`` reads the array's metadata
    again (a request in an object store), so a pass over chunks opens its arrays here and keeps them."""
    return {name: store_array(group, name) for name in names}
