"""Labelled datasets: chunked sampling, simulation and the Zarr store layout.

A dataset is generated chunk by chunk. Chunk i draws its rows from a generator seeded by (seed, i), so
the bytes of a chunk never depend on which process writes it or in which order. Each chunk writes its own
row range of every array, then marks itself complete in ``chunk_done``: a chunk whose mark is set is
complete, and a re-run skips it. The loop over the chunks is :func:`mpi_lidar.workflows.generate.generate`.

Layout (Zarr v3, one group): ``features`` float32 (n, 2F) = [depth per frequency, amplitude per frequency];
``target`` float64 (n,) true d_AS [m]; ``theta`` float64 (n, 6) scene parameters; ``split`` uint8 (n,)
0 = train, 1 = test; ``chunk_done`` uint8 (chunks,). Root attributes carry the schema, frequencies,
feature and theta names, the configuration and its SHA-256, and the package version.

The parts, each private: ``_chunks`` (the sampling plan and the simulation of a chunk), ``_layout`` (the
schema, built and checked), ``_store`` (creating, opening and writing a store), ``_readers`` (verified reads
of a complete store) and ``_summary`` (the raw errors of a dataset).
"""

from __future__ import annotations

from mpi_lidar.simulation.dataset._chunks import (
    NO_WRAP_SHARE,
    SPLIT_CODES,
    Chunk,
    SamplingPlan,
    cached_sensor,
    prior_wraps,
    seeded_rng,
    simulate_chunk,
    simulate_rows,
)
from mpi_lidar.simulation.dataset._layout import (
    ARRAY_DESCRIPTIONS,
    ARRAYS,
    DATA_ARRAYS,
    SCHEMA,
    frequency_labels,
    raw_feature_names,
)
from mpi_lidar.simulation.dataset._readers import (
    DatasetInfo,
    LazyDataset,
    Subsample,
    dataset_info,
    read_lazy,
    read_subsample,
    read_verified,
    read_verified_chunk,
    verify_dataset,
)
from mpi_lidar.simulation.dataset._store import (
    chunk_fingerprints,
    completed_chunks,
    create_store,
    incomplete_chunks,
    is_complete,
    open_store,
    store_config,
    store_key,
    write_chunk,
)
from mpi_lidar.simulation.dataset._summary import SUMMARY_STREAM, DatasetSummary, summarize

__all__ = [
    "ARRAYS", "ARRAY_DESCRIPTIONS", "DATA_ARRAYS", "NO_WRAP_SHARE", "SCHEMA", "SPLIT_CODES", "SUMMARY_STREAM",
    "Chunk", "DatasetInfo", "DatasetSummary", "LazyDataset", "SamplingPlan", "Subsample", "cached_sensor",
    "chunk_fingerprints", "completed_chunks", "create_store", "dataset_info", "frequency_labels",
    "incomplete_chunks", "is_complete", "open_store", "prior_wraps", "raw_feature_names", "read_lazy",
    "read_subsample", "read_verified", "read_verified_chunk", "seeded_rng", "simulate_chunk", "simulate_rows",
    "store_config", "store_key", "summarize", "verify_dataset", "write_chunk",
]
