"""Faults a cluster run meets: a worker killed, database connections cut, a batch interrupted, a bad output path.

A worker killed mid-generation and a worker killed mid-tuning on a LocalCluster are tested beside the code
they exercise (tests/test_dataset.py, tests/test_tune.py); here they hit ``dask worker`` processes.
"""

from __future__ import annotations

import os
import re
import signal
import subprocess
import threading
import time
from pathlib import Path

import numpy as np
import optuna
import pytest
import zarr
from distributed import Client
from optuna.trial import TrialState

from mpi_lidar.config import Config
from mpi_lidar.correction import CorrectionOptions
from mpi_lidar.learning import tune
from mpi_lidar.learning.features import FeatureSpec
from mpi_lidar.scans.store import write_scan
from mpi_lidar.workflows.correct_archive import correct_archive
from mpi_lidar.workflows.generate import generate
from tests.integration.conftest import (
    BIN,
    REPO,
    DaskCluster,
    database_url,
    run_cli,
    stop_group,
    subprocess_env,
    terminate_connections,
)
from tests.scan_factory import two_path_scan

pytestmark = pytest.mark.slow

SCAN_OUTPUTS = {"corrected.zarr", "maps.png", "error_hist.png", "point_cloud.png", "raw.ply", "corrected.ply",
                "corrected.laz", "report.md", "report.html", "metrics.json", ".mpi-lidar-report", "thumbnail.png"}
STAGING = re.compile(r"^\.scan\d{3}\.writing-[0-9a-f]{8}$")
BATCH = 4  # scans of a batch on the cluster: two workers, so a killed one has a scan to lose and more queued
CLI_BATCH = 4  # scans of the command-line batch killed after the first two


def write_archive(root: Path, count: int, height: int = 24, width: int = 32) -> Path:
    for index in range(count):
        write_scan(two_path_scan(f"scan{index:03d}", height, width, seed=index), root / f"scan{index:03d}.scan.zarr")
    return root


def corrected_depths(out: Path) -> dict[str, bytes]:
    return {p.name: zarr.open_group(str(p / "corrected.zarr"), mode="r")["corrected_depth"][:].tobytes()
            for p in sorted(out.iterdir()) if p.is_dir() and not p.name.startswith(".") and p.name != "summary"}


def kill_one_worker_once(client: Client) -> tuple[threading.Event, object]:
    """A callback that SIGKILLs one worker process the first time it is called (its nanny starts a new one)."""
    victim = sorted(client.run(os.getpid).values())[0]
    killed = threading.Event()

    def kill(_result: object) -> None:
        if not killed.is_set():
            killed.set()
            os.kill(victim, signal.SIGKILL)

    return killed, kill


def test_generate__worker_process_killed_completes_identically(tmp_path: Path, dask_cluster: DaskCluster) -> None:
    config = Config().replace(dataset={"samples": 1_600, "chunk_rows": 200, "seed": 9},
                              simulator={"fidelity": "waveform"})
    generate(tmp_path / "reference.zarr", config)
    with Client(dask_cluster.address) as client:
        killed, kill = kill_one_worker_once(client)
        report = generate(tmp_path / "killed.zarr", config, client, on_chunk=kill)
    dask_cluster.wait_for_workers(2)
    assert killed.is_set() and report.chunks_written == 8
    for name in ("features", "target", "theta", "split"):
        left = zarr.open_group(str(tmp_path / "killed.zarr"), mode="r")[name][:]
        right = zarr.open_group(str(tmp_path / "reference.zarr"), mode="r")[name][:]
        assert left.tobytes() == right.tobytes(), name


def test_correct_archive__worker_process_killed_mid_batch_completes_identically(
    tmp_path: Path, dask_cluster: DaskCluster, cluster_model: Path
) -> None:
    archive = write_archive(tmp_path / "archive", BATCH)
    out, reference = tmp_path / "out", tmp_path / "reference"
    with Client(dask_cluster.address) as client:
        killed, kill = kill_one_worker_once(client)
        outcomes = correct_archive([str(archive)], cluster_model, out, CorrectionOptions(), client, on_scan=kill)
    dask_cluster.wait_for_workers(2)
    assert killed.is_set()
    # planes with no facing surface: nothing to correct under the geometry gate, so every scan is unchanged
    assert [o.status for o in outcomes] == ["unchanged"] * BATCH
    # the output level never changes a pixel: the reference writes the corrected stores alone
    correct_archive([str(archive)], cluster_model, reference, CorrectionOptions(), outputs="data")
    assert corrected_depths(out) == corrected_depths(reference)
    assert all(set(os.listdir(out / f"scan{i:03d}")) == SCAN_OUTPUTS for i in range(BATCH))
    assert_only_staging_debris(out, [f"scan{i:03d}" for i in range(BATCH)])


def assert_only_staging_debris(out: Path, scans: list[str]) -> None:
    """Beside complete scan directories (and the batch's plotly.js), a killed writer leaves at most hidden staging
    directories."""
    extra = sorted(set(os.listdir(out)) - {*scans, "summary", "plotly.min.js"})
    assert all(STAGING.match(name) for name in extra), extra


def test_tune__worker_process_killed_mid_study_on_postgresql_loses_at_most_its_trial(
    dask_cluster: DaskCluster, small_dataset: Path, pg_database: str
) -> None:
    url = database_url(pg_database)
    settings = tune.TuneSettings(str(small_dataset), FeatureSpec(Config().frequencies_hz), tune_rows=1_000,
                                 num_boost_round=100, early_stopping_rounds=100)
    with Client(dask_cluster.address) as client:
        killed, kill = kill_one_worker_once(client)
        report = tune.tune(client, url, "killed", settings, trials=5, on_trial=kill)
    dask_cluster.wait_for_workers(2)
    trials = optuna.load_study(study_name="killed", storage=tune.normalise_storage_url(url)).get_trials()
    assert killed.is_set() and report.complete + report.pruned >= 5
    assert sorted(t.number for t in trials) == list(range(len(trials)))
    assert sum(t.state in tune.FINISHED for t in trials) >= 5
    assert sum(t.state in (TrialState.RUNNING, TrialState.FAIL) for t in trials) <= 1


def test_tune__postgresql_connections_terminated_mid_study_resumes_without_lost_or_duplicated_trials(
    dask_cluster: DaskCluster, small_dataset: Path, pg_database: str
) -> None:
    url = database_url(pg_database)
    settings = tune.TuneSettings(str(small_dataset), FeatureSpec(Config().frequencies_hz), tune_rows=2_000,
                                 num_boost_round=60, early_stopping_rounds=60)
    cuts: list[int] = []

    def cut_connections(_number: int) -> None:
        if len(cuts) < 2:
            cuts.append(terminate_connections(pg_database))

    with Client(dask_cluster.address) as client:
        report = tune.tune(client, url, "cut", settings, trials=6, on_trial=cut_connections)
        again = tune.tune(client, url, "cut", settings, trials=6)
    assert cuts and cuts[0] >= 1, "no connection was open to terminate"
    study = optuna.load_study(study_name="cut", storage=tune.normalise_storage_url(url))
    trials = study.get_trials(deepcopy=False)
    finished = [t for t in trials if t.state in tune.FINISHED]
    assert len(finished) == 6 and report.complete + report.pruned == 6 and again.trials_run == 0
    assert sorted(t.number for t in trials) == list(range(len(trials))), "a trial number is missing or doubled"
    assert len({tuple(sorted(t.params.items())) for t in finished}) == 6, "two trials ran the same parameters"
    interrupted = [t for t in trials if t.state not in tune.FINISHED]
    assert len(interrupted) <= 2 * len(cuts), "more trials failed than were running at the cuts (2 workers)"
    assert all(t.state in (TrialState.FAIL, TrialState.RUNNING) for t in interrupted)


def test_correct_cli__killed_batch_rerun_skips_finished_and_leaves_no_partial_outputs(
    tmp_path: Path, cluster_model: Path
) -> None:
    archive = write_archive(tmp_path / "archive", CLI_BATCH)
    out = tmp_path / "out"
    command = [str(BIN / "mpi-lidar"), "correct", str(archive), "--model", str(cluster_model), "--out", str(out),
               "--workers", "0", "--outputs", "full"]
    process = subprocess.Popen(command, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, env=subprocess_env(),
                               cwd=REPO, start_new_session=True)
    deadline = time.monotonic() + 180
    while time.monotonic() < deadline and len(corrected_dirs(out)) < 2 and process.poll() is None:
        time.sleep(0.05)
    stop_group(process)
    finished = corrected_dirs(out)
    assert 2 <= len(finished) < CLI_BATCH, "the kill should land part-way through the batch"
    assert all(set(os.listdir(out / name)) == SCAN_OUTPUTS for name in finished), "a visible output is partial"
    before = {name: (out / name / "metrics.json").stat().st_mtime_ns for name in finished}

    rerun = run_cli(*command[1:])
    names = [f"scan{i:03d}" for i in range(CLI_BATCH)]
    assert f"{CLI_BATCH} scans" in rerun.stdout and f"{len(finished)} already done" in rerun.stdout
    assert {name: (out / name / "metrics.json").stat().st_mtime_ns for name in finished} == before
    assert corrected_dirs(out) == names
    assert all(set(os.listdir(out / name)) == SCAN_OUTPUTS for name in names)
    # the batch's one plotly.js bundle (full outputs) beside the scans' folders, and no staging debris
    assert sorted(os.listdir(out)) == sorted([*names, "plotly.min.js", "summary"]), "no staging debris"
    depth = zarr.open_group(str(out / names[-1] / "corrected.zarr"), mode="r")["corrected_depth"][:]
    assert depth.shape == (24, 32) and np.isfinite(depth).all()


def corrected_dirs(out: Path) -> list[str]:
    if not out.is_dir():
        return []
    return sorted(p.name for p in out.iterdir() if p.is_dir() and not p.name.startswith(".") and p.name != "summary")


@pytest.mark.parametrize("command", ["simulate", "correct"])
def test_cli__unwritable_output_fails_with_one_error_line(tmp_path: Path, cluster_model: Path, command: str) -> None:
    blocker = tmp_path / "a-file"
    blocker.write_text("not a directory")
    if command == "simulate":
        args = ["simulate", "--out", str(blocker / "dataset.zarr"), "--samples", "1000", "--workers", "0"]
    else:
        archive = write_archive(tmp_path / "archive", 1)
        args = ["correct", str(archive), "--model", str(cluster_model), "--out", str(blocker / "out"),
                "--workers", "0"]
    result = run_cli(*args, check=False)
    lines = result.stderr.strip().splitlines()
    assert result.returncode == 2, result.stderr
    assert len(lines) == 1 and lines[0].startswith("error: ") and str(blocker) in lines[0]
    assert blocker.read_text() == "not a directory"
