"""Damage that must never be read as data: fingerprints gone or partial, arrays gone, declared sizes no reader
may allocate, and chunk files that are links, FIFOs or larger than a chunk can be.

Every store is written by the project's own writers and damaged by deleting or editing its files.
"""

from __future__ import annotations

import json
import os
import shutil
import time
import tracemalloc
from pathlib import Path

import numpy as np
import pytest
import zarr
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from mpi_lidar.config import Config
from mpi_lidar.errors import MpiLidarError, StoreError
from mpi_lidar.scans.scan import ScanError
from mpi_lidar.scans.store import read_scan, write_scan
from mpi_lidar.simulation import dataset
from mpi_lidar.storage.integrity import (
    CHUNK_FILE_SLACK_BYTES,
    MAX_CHUNK_VALUES,
    IntegrityError,
    fingerprints_required,
)
from mpi_lidar.workflows.verify import verify_store
from tests.cli_runner import assert_one_error_line, call_main
from tests.scan_factory import two_path_scan

SCAN_READERS = {"read_scan": read_scan, "verify": verify_store,
                "read_scan (kept in its store)": lambda p: read_scan(p, stored_above_bytes=0)}
DATASET_READERS = {
    "verify": verify_store,
    "training (lazy)": lambda p: dataset.read_lazy(p).features.sum().compute(),
    "tuning and evaluation (subsample)": lambda p: dataset.read_subsample(p, "test"),
    "summary": lambda p: dataset.summarize(p, noise_only_rows=10),
}


@pytest.fixture(scope="module")
def scan_store(tmp_path_factory) -> Path:
    """A 2 x 20 x 24 scan in chunks of (1, 20, 24): depth chunks 0/0/0 and 1/0/0."""
    return write_scan(two_path_scan("frame", height=20, width=24), tmp_path_factory.mktemp("scan") / "f.scan.zarr")


@pytest.fixture(scope="module")
def dataset_store(tmp_path_factory) -> Path:
    path = tmp_path_factory.mktemp("dataset") / "d.zarr"
    config = Config().replace(dataset={"samples": 400, "chunk_rows": 100, "seed": 3})
    dataset.create_store(path, config)
    for index in range(4):
        dataset.write_chunk(path, config, index)
    return path


def copied(store: Path, tmp_path: Path) -> Path:
    copy = tmp_path / store.name
    shutil.copytree(store, copy)
    return copy


def edit_attrs(store: Path, edit) -> None:
    """Edit a store's root attributes in its zarr.json (the copy readers use; consolidated metadata left as is)."""
    meta = json.loads((store / "zarr.json").read_text())
    edit(meta["attributes"])
    (store / "zarr.json").write_text(json.dumps(meta))


def edit_array(store: Path, name: str, **fields) -> None:
    """Edit an array's metadata: its ``shape`` and/or ``chunk_shape``."""
    meta = json.loads((store / name / "zarr.json").read_text())
    if "shape" in fields:
        meta["shape"] = fields["shape"]
    if "chunk_shape" in fields:
        meta["chunk_grid"]["configuration"]["chunk_shape"] = fields["chunk_shape"]
    (store / name / "zarr.json").write_text(json.dumps(meta))


@pytest.mark.unit
def test_fingerprints_required__every_version_of_every_store():
    for schema in ("mpi-lidar/scan@1", "mpi-lidar/dataset@1", "mpi-lidar/corrected@1", "mpi-lidar/scan@7"):
        assert fingerprints_required(schema)
    assert not any(fingerprints_required(s) for s in (None, "", "mpi-lidar/scan", "other/scan@1", 3))


# --- fingerprints gone or partial ---------------------------------------------------------------------------


@pytest.mark.unit
@pytest.mark.parametrize("reader", sorted(SCAN_READERS))
def test_scan_without_fingerprints_and_a_chunk_gone__damaged(scan_store, tmp_path, reader):
    copy = copied(scan_store, tmp_path)
    edit_attrs(copy, lambda attrs: attrs.pop("chunk_sha256"))
    (copy / "depth" / "c" / "1" / "0" / "0").unlink()
    with pytest.raises(IntegrityError, match=r"chunk fingerprints .* missing"):
        SCAN_READERS[reader](copy)


@pytest.mark.unit
@pytest.mark.parametrize("reader", sorted(SCAN_READERS))
def test_scan_with_one_arrays_fingerprints_removed__damaged(scan_store, tmp_path, reader):
    copy = copied(scan_store, tmp_path)
    edit_attrs(copy, lambda attrs: attrs["chunk_sha256"].pop("depth"))
    (copy / "depth" / "c" / "1" / "0" / "0").unlink()  # would read as zeros without its fingerprints
    with pytest.raises(IntegrityError, match="'depth' has no recorded fingerprints"):
        SCAN_READERS[reader](copy)


@pytest.mark.unit
@pytest.mark.parametrize("array", ["depth", "reference_depth", "azimuth_rad"])
@pytest.mark.parametrize("reader", sorted(SCAN_READERS))
def test_scan_with_an_array_removed__refused_by_every_reader(scan_store, tmp_path, reader, array):
    copy = copied(scan_store, tmp_path)
    shutil.rmtree(copy / array)
    with pytest.raises(IntegrityError, match=f"'{array}' is recorded in its fingerprints but gone"):
        SCAN_READERS[reader](copy)


@pytest.mark.unit
def test_scan_fingerprints_of_the_wrong_count_or_form__damaged(scan_store, tmp_path):
    copy = copied(scan_store, tmp_path)
    edit_attrs(copy, lambda attrs: attrs["chunk_sha256"]["depth"].pop())
    with pytest.raises(IntegrityError, match="'depth' are not one per chunk"):
        read_scan(copy)
    edit_attrs(copy, lambda attrs: attrs["chunk_sha256"].update(depth=["zz" * 32, "00" * 32]))
    with pytest.raises(IntegrityError, match="'depth' are not one per chunk"):
        read_scan(copy)


@pytest.mark.unit
@pytest.mark.parametrize("reader", sorted(DATASET_READERS))
def test_dataset_without_fingerprint_array__damaged_for_every_reader(dataset_store, tmp_path, reader):
    copy = copied(dataset_store, tmp_path)
    shutil.rmtree(copy / "chunk_sha256")
    (copy / "features" / "c" / "1" / "0").unlink()
    with pytest.raises(StoreError, match="lacks 'chunk_sha256'"):
        DATASET_READERS[reader](copy)


@pytest.mark.unit
@pytest.mark.parametrize("reader", sorted(DATASET_READERS))
def test_dataset_fingerprint_chunk_deleted__its_rows_are_not_read(dataset_store, tmp_path, reader):
    copy = copied(dataset_store, tmp_path)
    (copy / "chunk_sha256" / "c" / "1" / "0" / "0").unlink()  # reads as zeros: no chunk hashes to that
    with pytest.raises(IntegrityError, match=r"chunk 1 of '(features|target|theta|split)'"):
        DATASET_READERS[reader](copy)


@pytest.mark.unit
def test_dataset_incomplete_chunk__never_read_as_fill_values(dataset_store, tmp_path):
    copy = copied(dataset_store, tmp_path)
    (copy / "chunk_done" / "c" / "2").unlink()
    for read in (lambda p: dataset.read_verified(p), lambda p: dataset.summarize(p, 10), verify_store):
        with pytest.raises(StoreError, match=r"incomplete \(3 of 4 chunks\)"):
            read(copy)


@pytest.mark.integration
def test_verify_cli__store_without_fingerprints_exits_1_with_one_line(scan_store, tmp_path, monkeypatch, capsys):
    copy = copied(scan_store, tmp_path)
    edit_attrs(copy, lambda attrs: attrs.pop("chunk_sha256"))
    code, out, err = call_main(monkeypatch, capsys, "verify", copy)
    assert code == 1 and "ok" not in out
    assert_one_error_line(err, "chunk fingerprints (chunk_sha256) are missing")


# --- declared sizes -----------------------------------------------------------------------------------------


@pytest.mark.unit
@pytest.mark.parametrize("fields", [{"shape": [2, 100_000, 100_000]},
                                    {"shape": [2, 100_000, 100_000], "chunk_shape": [1, 100_000, 100_000]},
                                    {"chunk_shape": [1, 100_000, 100_000]}])
@pytest.mark.parametrize("reader", sorted(SCAN_READERS))
def test_scan_declaring_huge_arrays_or_chunks__refused_before_allocating(scan_store, tmp_path, reader, fields):
    copy = copied(scan_store, tmp_path)
    edit_array(copy, "depth", **fields)
    tracemalloc.start()
    try:
        with pytest.raises((IntegrityError, ScanError), match="declares"):
            SCAN_READERS[reader](copy)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert peak < 64 * 2**20, f"{peak / 2**20:.0f} MiB allocated before refusing"


@pytest.mark.unit
def test_dataset_declaring_huge_chunks__refused_before_allocating(dataset_store, tmp_path):
    copy = copied(dataset_store, tmp_path)
    edit_array(copy, "features", chunk_shape=[MAX_CHUNK_VALUES, 8])
    with pytest.raises(StoreError, match="in chunks of"):
        dataset.read_subsample(copy, "test")
    copy2 = copied(dataset_store, tmp_path / "2")
    edit_attrs(copy2, lambda attrs: attrs.update(samples=10**12))
    with pytest.raises(StoreError, match="beyond what a dataset may hold"):
        verify_store(copy2)


# --- chunk files that are not what a chunk can be -------------------------------------------------------------


@pytest.mark.unit
@pytest.mark.parametrize("reader", sorted(SCAN_READERS))
def test_scan_chunk_linked_to_dev_zero__refused_before_reading(scan_store, tmp_path, reader):
    copy = copied(scan_store, tmp_path)
    chunk = copy / "depth" / "c" / "1" / "0" / "0"
    chunk.unlink()
    chunk.symlink_to("/dev/zero")
    started = time.perf_counter()
    with pytest.raises(IntegrityError, match=r"depth/c/1/0/0 is a symbolic link"):
        SCAN_READERS[reader](copy)
    assert time.perf_counter() - started < 10


@pytest.mark.unit
@pytest.mark.parametrize("reader", sorted(SCAN_READERS))
def test_scan_chunk_that_is_a_fifo__refused_without_hanging(scan_store, tmp_path, reader):
    copy = copied(scan_store, tmp_path)
    chunk = copy / "amplitude" / "c" / "0" / "0" / "0"
    chunk.unlink()
    os.mkfifo(chunk)
    with pytest.raises(IntegrityError, match=r"amplitude/c/0/0/0 is not a regular file"):
        SCAN_READERS[reader](copy)


@pytest.mark.unit
def test_scan_metadata_linked__refused(scan_store, tmp_path):
    copy = copied(scan_store, tmp_path)
    (copy / "depth" / "zarr.json").unlink()
    (copy / "depth" / "zarr.json").symlink_to(scan_store / "depth" / "zarr.json")
    with pytest.raises(IntegrityError, match=r"depth/zarr\.json is a symbolic link"):
        read_scan(copy)


@pytest.mark.unit
@pytest.mark.parametrize("reader", sorted(SCAN_READERS))
def test_scan_chunk_file_larger_than_a_chunk__refused_before_reading(scan_store, tmp_path, reader):
    copy = copied(scan_store, tmp_path)
    chunk = copy / "depth" / "c" / "0" / "0" / "0"
    os.truncate(chunk, 2**40)  # sparse: a terabyte that takes no disk
    with pytest.raises(IntegrityError, match=r"depth/c/0/0/0 takes 1,099,511,627,776 bytes"):
        SCAN_READERS[reader](copy)


@pytest.mark.unit
def test_dataset_chunk_linked_or_oversized__refused_by_every_reader(dataset_store, tmp_path):
    copy = copied(dataset_store, tmp_path)
    chunk = copy / "target" / "c" / "2"
    chunk.unlink()
    chunk.symlink_to("/dev/zero")
    for read in DATASET_READERS.values():
        with pytest.raises(IntegrityError, match="target/c/2 is a symbolic link"):
            read(copy)
    chunk.unlink()
    with open(chunk, "wb") as file:
        file.truncate(100 * 8 + CHUNK_FILE_SLACK_BYTES + 1)
    for read in DATASET_READERS.values():
        with pytest.raises(IntegrityError, match="target/c/2 takes"):
            read(copy)


@pytest.mark.unit
def test_every_refusal__is_one_line(scan_store, tmp_path):
    copy = copied(scan_store, tmp_path)
    (copy / "depth" / "c" / "1" / "0" / "0").unlink()
    (copy / "depth" / "c" / "1" / "0" / "0").symlink_to("/dev/zero")
    with pytest.raises(MpiLidarError) as caught:
        read_scan(copy)
    assert "\n" not in str(caught.value) and str(copy) in str(caught.value)
    assert zarr.open_group(store=str(scan_store), mode="r").attrs["schema"] == "mpi-lidar/scan@1", "source intact"


# --- a large scan kept in its store: every band read is checked again -----------------------------------------


@pytest.mark.unit
@pytest.mark.parametrize("read", ["whole", "band of rows", "one frequency", "ellipsis", "pixels", "c-order parts"])
def test_stored_map__chunk_deleted_after_opening__never_read_as_fill_values(scan_store, tmp_path, read):
    from mpi_lidar.scans.stored_map import StoredMap

    copy = copied(scan_store, tmp_path)
    scan = read_scan(copy, stored_above_bytes=0)
    depth = scan.depth
    assert isinstance(depth, StoredMap)
    (copy / "depth" / "c" / "1" / "0" / "0").unlink()  # after the store was checked, before correction reads it
    reads = {"whole": lambda: np.asarray(depth), "band of rows": lambda: depth[:, 2:5],
             "one frequency": lambda: depth[-1], "ellipsis": lambda: depth[..., 3],
             "pixels": lambda: depth[:, np.array([0, 3]), np.array([1, 2])],
             "c-order parts": lambda: list(depth.c_order_parts())}
    with pytest.raises(IntegrityError, match=r"chunk \(1, 0, 0\) of 'depth'"):
        reads[read]()


@pytest.mark.unit
def test_stored_map__intact_reads_are_the_arrays_values(scan_store):
    memory, stored = read_scan(scan_store), read_scan(scan_store, stored_above_bytes=0)
    np.testing.assert_array_equal(stored.depth[-1], memory.depth[-1])
    np.testing.assert_array_equal(stored.depth[0, 3:7, 2], memory.depth[0, 3:7, 2])
    np.testing.assert_array_equal(np.concatenate([p.reshape(-1) for p in stored.depth.c_order_parts()]),
                                  memory.depth.reshape(-1))


@pytest.mark.integration
def test_evaluate_cli__dataset_without_fingerprints_exits_2_with_one_line(dataset_store, tmp_path, monkeypatch,
                                                                          capsys):
    from tests.model_factory import tiny_model

    model = tiny_model(tmp_path / "model", geometric=False, feature_set="raw", rounds=3, rows=500)
    copy = copied(dataset_store, tmp_path)
    shutil.rmtree(copy / "chunk_sha256")
    (copy / "features" / "c" / "1" / "0").unlink()
    code, out, err = call_main(monkeypatch, capsys, "evaluate", "--data", copy, "--model", model,
                               "--out", tmp_path / "report")
    assert code == 2 and "MAE" not in out
    assert_one_error_line(err, "lacks 'chunk_sha256'")
    assert not (tmp_path / "report").exists(), "nothing written"


# --- any mix of the above: what a reader returns is what was written, or it refuses ---------------------------

HARMS = st.lists(st.tuples(st.sampled_from(["drop fingerprints", "drop an entry", "shorten an entry", "delete chunk",
                                            "swap chunk", "remove array"]),
                           st.integers(0, 10**6)), min_size=1, max_size=3)


def _harm(store: Path, harms: list[tuple[str, int]]) -> None:
    for how, pick in harms:
        arrays = sorted(p.name for p in store.iterdir() if p.is_dir())
        chunks = sorted(p for p in store.rglob("*") if p.is_file() and p.parent.name != store.name
                        and p.name != "zarr.json")
        if how == "drop fingerprints":
            edit_attrs(store, lambda attrs: attrs.pop("chunk_sha256", None))
        elif how in ("drop an entry", "shorten an entry"):
            def edit(attrs, how=how, pick=pick):
                recorded = attrs.get("chunk_sha256")
                if isinstance(recorded, dict) and recorded:
                    name = sorted(recorded)[pick % len(recorded)]
                    if how == "drop an entry":
                        recorded.pop(name)
                    else:
                        recorded[name] = recorded[name][:-1]
            edit_attrs(store, edit)
        elif how == "delete chunk" and chunks:
            chunks[pick % len(chunks)].unlink()
        elif how == "swap chunk" and len(chunks) > 1:
            source, target = chunks[pick % len(chunks)], chunks[(pick + 1) % len(chunks)]
            shutil.copyfile(source, target)
        elif how == "remove array" and arrays:
            shutil.rmtree(store / arrays[pick % len(arrays)])


@pytest.mark.unit
@settings(max_examples=40, deadline=None, derandomize=True,
          suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow])
@given(harms=HARMS)
def test_read_scan__damage_of_any_mix_is_refused_or_read_as_written(scan_store, tmp_path_factory, harms):
    copy = copied(scan_store, tmp_path_factory.mktemp("mix"))
    intact = read_scan(scan_store)
    _harm(copy, harms)
    for read in SCAN_READERS.values():
        try:
            result = read(copy)
        except MpiLidarError as exc:
            assert "\n" not in str(exc)
            continue
        if hasattr(result, "depth"):  # read_scan: exactly the values written
            np.testing.assert_array_equal(np.asarray(result.depth), intact.depth)
            np.testing.assert_array_equal(np.asarray(result.amplitude), intact.amplitude)
            assert result.content_sha256() == intact.content_sha256()


@pytest.mark.unit
def test_chunk_linked_after_opening__refused_where_it_is_read(scan_store, dataset_store, tmp_path):
    scan_copy = copied(scan_store, tmp_path)
    depth = read_scan(scan_copy, stored_above_bytes=0).depth
    chunk = scan_copy / "depth" / "c" / "0" / "0" / "0"
    chunk.unlink()
    chunk.symlink_to("/dev/zero")
    with pytest.raises(IntegrityError, match=r"depth/c/0/0/0 is not a regular file"):
        np.asarray(depth)
    data_copy = copied(dataset_store, tmp_path)
    lazy = dataset.read_lazy(data_copy)  # opened and checked; each block is read where it is computed
    chunk = data_copy / "features" / "c" / "3" / "0"
    chunk.unlink()
    os.mkfifo(chunk)
    with pytest.raises(IntegrityError, match=r"features/c/3/0 is not a regular file"):
        lazy.features.sum().compute()
