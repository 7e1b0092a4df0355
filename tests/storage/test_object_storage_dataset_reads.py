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
# Metadata a pass reads once, whatever the chunks: the root's and, for open_store's checks, each of the six
# arrays' twice; then the completion marks', the fingerprints' and the four data arrays'.
METADATA_PER_PASS = 1 + 2 * 6 + 2 + 4


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
