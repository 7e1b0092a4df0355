"""A deleted, truncated or swapped chunk is detected by every reader: datasets, scans and corrected outputs."""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pytest

from mpi_lidar.config import Config
from mpi_lidar.errors import StoreError
from mpi_lidar.scans.store import read_scan, write_scan
from mpi_lidar.simulation import dataset
from mpi_lidar.storage.integrity import IntegrityError, array_fingerprints, fingerprint
from mpi_lidar.workflows.verify import verify_store
from tests.scan_factory import two_path_scan

pytestmark = pytest.mark.unit

DAMAGES = ("deleted", "truncated", "swapped")


def damage(store: Path, array: str, chunk: str, other: str, how: str) -> None:
    """Damage one chunk file of a Zarr v3 store the way a disk, a sync tool or a person would."""
    target = store / array / "c" / chunk
    if how == "deleted":
        target.unlink()
    elif how == "truncated":
        target.write_bytes(target.read_bytes()[: len(target.read_bytes()) // 3])
    else:
        shutil.copyfile(store / array / "c" / other, target)


@pytest.fixture(scope="module")
def store(tmp_path_factory) -> Path:
    path = tmp_path_factory.mktemp("integrity") / "d.zarr"
    config = Config().replace(dataset={"samples": 2_000, "chunk_rows": 500, "seed": 5})
    dataset.create_store(path, config)
    for index in range(4):
        dataset.write_chunk(path, config, index)
    return path


CONSUMERS = {
    "verify": lambda p: verify_store(p),
    "training (lazy, streaming)": lambda p: [a.sum().compute() for a in vars(dataset.read_lazy(p)).values()
                                             if hasattr(a, "compute")],
    "tuning and evaluation (subsample)": lambda p: dataset.read_subsample(p, "test"),
    "summary": lambda p: dataset.summarize(p, noise_only_rows=10),
}


def test_fingerprint__depends_on_values_dtype_and_shape():
    values = np.arange(6, dtype=np.float32)
    assert fingerprint(values) == fingerprint(values.copy())
    assert fingerprint(values) != fingerprint(values.astype(np.float64))
    assert fingerprint(values) != fingerprint(values.reshape(2, 3))
    assert len(array_fingerprints(np.zeros((5, 4)), (2, 4))) == 3


def test_intact_store__every_consumer_reads_it(store):
    for consume in CONSUMERS.values():
        consume(store)
    assert verify_store(store).chunks == 4


@pytest.mark.parametrize("array", ["features", "split"])
@pytest.mark.parametrize("how", DAMAGES)
@pytest.mark.parametrize("consumer", sorted(CONSUMERS))
def test_damaged_dataset_chunk__detected_by_every_consumer(store, tmp_path, array, how, consumer):
    copy = tmp_path / "d.zarr"
    shutil.copytree(store, copy)
    chunk, other = ("2/0", "1/0") if array == "features" else ("2", "1")
    damage(copy, array, chunk, other, how)
    with pytest.raises(IntegrityError, match=rf"chunk \(?2.* of '{array}'"):
        CONSUMERS[consumer](copy)


@pytest.mark.parametrize("how", DAMAGES)
def test_damaged_scan_chunk__refused_when_read(tmp_path, how):
    path = write_scan(two_path_scan("frame", height=8, width=6), tmp_path / "frame.scan.zarr")
    assert read_scan(path).name == "frame"
    damage(path, "depth", "2/0/0", "1/0/0", how)
    with pytest.raises(IntegrityError, match=r"chunk \(2, 0, 0\) of 'depth'"):
        read_scan(path)
    with pytest.raises(IntegrityError):
        verify_store(path)


@pytest.mark.parametrize("consumer", sorted(CONSUMERS))
def test_dataset_without_fingerprints__damaged_for_every_consumer(store, tmp_path, consumer):
    """Its schema version records fingerprints: without them (and a chunk gone) the store is damaged, not old."""
    copy = tmp_path / "old.zarr"
    shutil.copytree(store, copy)
    shutil.rmtree(copy / "chunk_sha256")
    (copy / "features" / "c" / "2" / "0").unlink()
    with pytest.raises(StoreError, match="lacks 'chunk_sha256'"):
        CONSUMERS[consumer](copy)


def test_two_swapped_scan_chunks__the_first_in_c_order_is_named(tmp_path, monkeypatch):
    monkeypatch.setattr("os.cpu_count", lambda: 4)  # the chunks are checked on several threads
    monkeypatch.delenv("OMP_NUM_THREADS", raising=False)
    path = write_scan(two_path_scan("frame", height=8, width=6), tmp_path / "frame.scan.zarr")
    damage(path, "depth", "3/0/0", "0/0/0", "swapped")
    damage(path, "depth", "1/0/0", "0/0/0", "swapped")
    for _ in range(5):  # whichever thread finds its damage first
        with pytest.raises(IntegrityError, match=r"chunk \(1, 0, 0\) of 'depth'"):
            read_scan(path)
