from __future__ import annotations

import os
import signal
import subprocess
import sys
import threading
import time
import warnings
from pathlib import Path

import numpy as np
import pytest
import xarray as xr
import zarr
from distributed import Client, LocalCluster

from mpi_lidar.config import Config
from mpi_lidar.errors import StoreError
from mpi_lidar.simulation import dataset
from mpi_lidar.workflows.generate import generate
from tests.cli_runner import call_main

ARRAY_NAMES = ("features", "target", "theta", "split")


def small_config(samples: int = 4_000, chunk_rows: int = 500, **simulator: object) -> Config:
    return Config().replace(dataset={"samples": samples, "chunk_rows": chunk_rows, "seed": 7}, simulator=simulator)


def read_arrays(path: Path) -> dict[str, np.ndarray]:
    group = zarr.open_group(str(path), mode="r")
    return {name: group[name][:] for name in ARRAY_NAMES}


def assert_same_bytes(a: Path, b: Path) -> None:
    left, right = read_arrays(a), read_arrays(b)
    for name in ARRAY_NAMES:
        assert left[name].dtype == right[name].dtype
        assert left[name].tobytes() == right[name].tobytes(), f"{name} differs"


@pytest.fixture(scope="module")
def two_worker_client():
    with LocalCluster(n_workers=2, threads_per_worker=1, processes=True, dashboard_address=":0") as cluster:
        with Client(cluster) as client:
            yield client


# A slow fidelity, so that a kill lands while chunks are still being written: 12 chunks of 40 rows.
KILLED_RUN = {"samples": 480, "chunk_rows": 40, "fidelity": "waveform"}


@pytest.fixture(scope="module")
def waveform_reference(tmp_path_factory) -> Path:
    """The uninterrupted in-process store of KILLED_RUN, shared by the tests that kill a run part-way."""
    path = tmp_path_factory.mktemp("waveform") / "reference.zarr"
    generate(path, small_config(**KILLED_RUN))
    return path


@pytest.fixture(scope="module")
def reference_store(tmp_path_factory) -> Path:
    path = tmp_path_factory.mktemp("reference") / "in_process.zarr"
    generate(path, small_config())
    return path


@pytest.mark.integration
def test_generate__one_and_two_workers_write_identical_bytes(tmp_path, reference_store, two_worker_client):
    with LocalCluster(n_workers=1, threads_per_worker=1, processes=True, dashboard_address=":0") as cluster:
        with Client(cluster) as one_worker:
            generate(tmp_path / "one.zarr", small_config(), one_worker)
    generate(tmp_path / "two.zarr", small_config(), two_worker_client)
    assert_same_bytes(tmp_path / "one.zarr", tmp_path / "two.zarr")
    assert_same_bytes(tmp_path / "two.zarr", reference_store)


@pytest.mark.unit
def test_generate__rerun_skips_complete_chunks(tmp_path):
    path = tmp_path / "d.zarr"
    first = generate(path, small_config())
    second = generate(path, small_config())
    assert (first.chunks_written, first.chunks_skipped) == (8, 0)
    assert (second.chunks_written, second.chunks_skipped) == (0, 8)


@pytest.mark.unit
def test_generate__partial_store_resumes_to_identical_bytes(tmp_path, reference_store):
    path = tmp_path / "partial.zarr"
    config = small_config()
    dataset.create_store(path, config)
    for index in (0, 3, 5):
        dataset.write_chunk(path, config, index)
    report = generate(path, config)
    assert report.chunks_written == 5
    assert_same_bytes(path, reference_store)


@pytest.mark.unit
def test_generate__unmarked_chunk_with_garbage_is_rewritten(tmp_path, reference_store):
    """A chunk whose data landed but whose completion mark did not (a kill in between) is redone."""
    path = tmp_path / "garbage.zarr"
    config = small_config()
    dataset.create_store(path, config)
    group = zarr.open_group(str(path), mode="r+")
    group["features"][0:500] = np.full((500, 8), 99.0, dtype=np.float32)
    generate(path, config)
    assert_same_bytes(path, reference_store)


@pytest.mark.slow
@pytest.mark.integration
def test_generate__worker_killed_mid_run_completes_identically(tmp_path, waveform_reference, two_worker_client):
    # the module's cluster: its nanny restarts the killed worker for whichever test comes next
    config = small_config(**KILLED_RUN)
    path = tmp_path / "killed.zarr"
    victim_pid = next(iter(two_worker_client.run(os.getpid).values()))
    killed = threading.Event()

    def kill_one_worker(_index: int) -> None:
        if not killed.is_set():
            killed.set()
            os.kill(victim_pid, signal.SIGKILL)

    report = generate(path, config, two_worker_client, on_chunk=kill_one_worker)
    assert killed.is_set()
    assert report.chunks_written == 12
    assert dataset.is_complete(path)
    assert_same_bytes(path, waveform_reference)


@pytest.mark.slow
@pytest.mark.integration
def test_simulate_cli__killed_process_rerun_matches_uninterrupted(tmp_path, monkeypatch, capsys, waveform_reference):
    args = ["--samples", str(KILLED_RUN["samples"]), "--chunk-rows", str(KILLED_RUN["chunk_rows"]),
            "--fidelity", str(KILLED_RUN["fidelity"]), "--workers", "0", "--seed", "7"]
    command = [sys.executable, "-m", "mpi_lidar.cli", "simulate"]
    killed = tmp_path / "killed.zarr"
    process = subprocess.Popen([*command, "--out", str(killed), *args], stdout=subprocess.DEVNULL,
                               stderr=subprocess.DEVNULL)
    deadline = time.monotonic() + 60
    while time.monotonic() < deadline and not _some_chunks_done(killed):
        time.sleep(0.05)
    process.send_signal(signal.SIGKILL)
    process.wait()
    done = zarr.open_group(str(killed), mode="r")["chunk_done"][:]
    assert 0 < done.sum() < done.size, "the kill should land part-way through"
    # only the kill needs a process of its own; the rerun is the command's, in this one
    code, _, stderr = call_main(monkeypatch, capsys, "simulate", "--out", killed, *args)
    assert code == 0, stderr
    assert_same_bytes(killed, waveform_reference)  # the command's rerun equals the uninterrupted run


def _some_chunks_done(path: Path) -> bool:
    try:
        return zarr.open_group(str(path), mode="r")["chunk_done"][:].any()
    except Exception:
        return False


@pytest.mark.unit
def test_create_store__other_configuration_is_refused_and_untouched(tmp_path, reference_store):
    other = small_config().replace(dataset={"seed": 8})
    before = read_arrays(reference_store)
    with pytest.raises(StoreError, match="another configuration"):
        dataset.create_store(reference_store, other)
    after = read_arrays(reference_store)
    assert all(before[name].tobytes() == after[name].tobytes() for name in ARRAY_NAMES)


@pytest.mark.unit
def test_create_store__foreign_zarr_store_is_refused(tmp_path):
    foreign = tmp_path / "foreign.zarr"
    zarr.open_group(str(foreign), mode="w").create_array("x", shape=(3,), dtype="f4")
    with pytest.raises(StoreError, match="not an mpi-lidar dataset"):
        dataset.create_store(foreign, small_config())


@pytest.mark.unit
def test_create_store__regular_file_is_refused(tmp_path):
    target = tmp_path / "notes.txt"
    target.write_text("mine")
    with pytest.raises(StoreError):
        dataset.create_store(target, small_config())
    assert target.read_text() == "mine"


@pytest.mark.unit
def test_create_store__read_only_parent_gives_clear_error_and_no_debris(tmp_path):
    if os.geteuid() == 0:
        # root ignores directory permissions; a read-only bind is not available here, so use /proc.
        parent = Path("/proc/self")
    else:
        parent = tmp_path / "ro"
        parent.mkdir()
        parent.chmod(0o500)
    with pytest.raises(StoreError, match=r"(cannot write dataset store|dataset store .* GiB free)"):
        dataset.create_store(parent / "d.zarr", small_config())
    assert not (parent / "d.zarr").exists()


@pytest.mark.unit
def test_open_store__truncated_store_is_refused(tmp_path, reference_store):
    import shutil

    broken = tmp_path / "broken.zarr"
    shutil.copytree(reference_store, broken)
    shutil.rmtree(broken / "theta")
    with pytest.raises(StoreError, match=r"truncated|damaged|not a readable"):
        dataset.open_store(broken)


@pytest.mark.unit
def test_open_store__missing_path_says_how_to_create_it(tmp_path):
    with pytest.raises(StoreError, match="mpi-lidar simulate"):
        dataset.open_store(tmp_path / "absent.zarr")


@pytest.mark.unit
def test_read_lazy__matches_stored_arrays(reference_store):
    lazy = dataset.read_lazy(reference_store)
    stored = read_arrays(reference_store)
    assert lazy.features.chunks[0][0] == 500
    np.testing.assert_array_equal(lazy.features.compute(), stored["features"])
    np.testing.assert_array_equal(lazy.target.compute(), stored["target"])
    assert lazy.info.frequencies_hz == Config().frequencies_hz
    assert lazy.info.config == small_config()


@pytest.mark.unit
def test_read_subsample__rows_belong_to_the_split_and_are_seeded(reference_store):
    stored = read_arrays(reference_store)
    sub = dataset.read_subsample(reference_store, split="test", max_rows=300, seed=1)
    again = dataset.read_subsample(reference_store, split="test", max_rows=300, seed=1)
    assert sub.rows.size == 300
    assert np.all(stored["split"][sub.rows] == dataset.SPLIT_CODES["test"])
    np.testing.assert_array_equal(sub.rows, again.rows)
    np.testing.assert_array_equal(sub.features, stored["features"][sub.rows])
    np.testing.assert_array_equal(sub.target, stored["target"][sub.rows])


@pytest.mark.unit
def test_read_lazy__incomplete_store_is_refused(tmp_path):
    path = tmp_path / "incomplete.zarr"
    config = small_config()
    dataset.create_store(path, config)
    dataset.write_chunk(path, config, 0)
    with pytest.raises(StoreError, match=r"incomplete \(1 of 8 chunks\)"):
        dataset.read_lazy(path)


@pytest.mark.unit
def test_simulate_chunk__split_share_is_exact_per_chunk():
    chunk = dataset.simulate_chunk(small_config(), 2)
    assert (chunk.split == dataset.SPLIT_CODES["test"]).sum() == 100
    assert chunk.features.dtype == np.float32 and chunk.target.dtype == np.float64


@pytest.mark.unit
def test_store__opens_with_xarray(reference_store):
    ds = xr.open_zarr(reference_store, consolidated=False)
    assert ds["features"].dims == ("sample", "feature")
    assert ds["features"].dtype == np.float32
    assert ds["target"].dtype == np.float64
    assert ds["split"].dtype == np.uint8
    assert ds.attrs["schema"] == dataset.SCHEMA
    assert ds.attrs["frequencies_hz"] == list(Config().frequencies_hz)


@pytest.mark.unit
def test_create_store__xarray_opens_it_without_warnings(tmp_path):
    config = small_config()
    path = tmp_path / "d.zarr"
    dataset.create_store(path, config)
    for index in range(dataset.SamplingPlan.from_config(config).chunks):
        dataset.write_chunk(path, config, index)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        opened = xr.open_zarr(path)
    assert opened.target.attrs["units"] == "m" and opened.split.attrs["flag_meanings"] == "train test"
    np.testing.assert_array_equal(opened.target.values, dataset.read_subsample(path, "all").target)
