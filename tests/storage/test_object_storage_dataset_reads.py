"""Requests of a dataset's read passes in a bucket: each array's metadata read once per pass, not once per chunk
(moto's S3 server on 127.0.0.1, the requests counted as the benchmark counts them)."""

from __future__ import annotations

import numpy as np
import pytest

from benchmarks.object_storage import OPERATIONS, install_counters, take_counters
from mpi_lidar.locations import location
from mpi_lidar.simulation import dataset
from mpi_lidar.storage import objects
from tests.storage.conftest import BUCKET

pytestmark = pytest.mark.integration

# Objects of one chunk that a verifying pass reads: the four data arrays' chunks, its completion mark and its
# fingerprints.
OBJECTS_PER_CHUNK = 6
# Metadata a pass reads once, whatever the chunks: the root's and each of the six arrays', opened by open_store's
# checks and kept for the reads (19 before the arrays were kept: each opened twice by the checks, four again).
METADATA_PER_PASS = 1 + 6


@pytest.fixture(scope="module")
def dataset_url(s3_server, small_dataset) -> str:
    """The session's small dataset (8,000 rows in 4 chunks), copied into the bucket: its URL."""
    url = f"s3://{BUCKET}/reads/dataset.zarr"
    objects.filesystem(location(url)).put(str(small_dataset) + "/", location(url).path, recursive=True)
    return url


def requests_of(action) -> dict[str, int]:
    install_counters()
    take_counters()
    action()
    return {name: int(n) for name, n in take_counters().items() if name in OPERATIONS}


def test_verify_dataset__metadata_read_once_per_pass(dataset_url):
    chunks = dataset.dataset_info(dataset_url).chunks
    asked = requests_of(lambda: dataset.verify_dataset(dataset_url))
    assert asked == {"ListObjectsV2": 1, "GetObject": METADATA_PER_PASS + OBJECTS_PER_CHUNK * chunks}, asked
    # A subsample reads the split of every chunk, then the chunks holding the rows, in the same pass.
    asked = requests_of(lambda: dataset.read_subsample(dataset_url, "test", max_rows=10, seed=1))
    assert asked["ListObjectsV2"] == 1 and asked["GetObject"] <= METADATA_PER_PASS + OBJECTS_PER_CHUNK * chunks


def test_read_lazy__each_block_reads_its_array_metadata_and_chunk_alone(dataset_url, small_dataset):
    """Where a block is computed it opens its array only: one metadata read and one chunk, no listing, no
    group metadata, no probe for another Zarr format."""
    lazy = dataset.read_lazy(dataset_url)
    blocks = lazy.target.numblocks[0]
    target: list[np.ndarray] = []
    asked = requests_of(lambda: target.append(lazy.target.compute(scheduler="sync")))
    assert asked == {"GetObject": 2 * blocks}, asked
    assert np.array_equal(target[0], dataset.read_verified(small_dataset, ("target",))["target"])


def test_write_chunk__complete_chunk_in_bucket_opens_store_as_zarr_v3(dataset_url):
    """A worker's write of a chunk already complete reads the root's metadata, the completion marks' and the
    mark: three requests, none a probe for Zarr v2 metadata (six before: .zgroup, .zattrs and .zmetadata)."""
    config = dataset.store_config(dataset.open_store(dataset_url))
    written: list[bool] = []
    asked = requests_of(lambda: written.append(dataset.write_chunk(dataset_url, config, 0)))
    assert written == [False]
    assert asked == {"GetObject": 3}, asked
