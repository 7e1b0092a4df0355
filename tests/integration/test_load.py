"""Load: four trial processes on one PostgreSQL study, and 200 scans in one batch, every one accounted for.

Throughput figures come from ``python -m benchmarks.cluster`` (docs/results/cluster.md), not from these tests.
"""

from __future__ import annotations

import json
import logging
from dataclasses import replace
from pathlib import Path

import optuna
import pytest
from distributed import Client, LocalCluster

from mpi_lidar.config import Config
from mpi_lidar.correction import CorrectionOptions
from mpi_lidar.learning import tune
from mpi_lidar.learning.features import FeatureSpec
from mpi_lidar.scans.store import write_scan
from mpi_lidar.workflows.correct_archive import correct_archive
from tests.integration.conftest import DaskCluster, database_url
from tests.scan_factory import two_path_scan

pytestmark = pytest.mark.slow

SCANS = 200
TRIALS = 8  # two rounds of four side by side


def write_small_scan(archive: Path, index: int) -> None:
    """One 8 x 8 scan without geometry (run on the cluster's workers, which write the archive side by side)."""
    scan = two_path_scan(f"s{index:03d}", 8, 8, seed=index)
    scan = replace(scan, azimuth_rad=None, elevation_rad=None, reference_depth=None, reference_mask=None)
    write_scan(scan, archive / f"s{index:03d}.scan.zarr")


def max_overlap(intervals: list[tuple[float, float]]) -> int:
    """The largest number of intervals open at one moment."""
    events = sorted([(start, 1) for start, _ in intervals] + [(end, -1) for _, end in intervals])
    open_now = best = 0
    for _, step in events:
        open_now += step
        best = max(best, open_now)
    return best


def test_tune__four_trial_processes_on_one_postgresql_study(small_dataset: Path, pg_database: str) -> None:
    url = database_url(pg_database)
    settings = tune.TuneSettings(str(small_dataset), FeatureSpec(Config().frequencies_hz), tune_rows=1_000,
                                 num_boost_round=20, early_stopping_rounds=20)
    with (LocalCluster(n_workers=4, threads_per_worker=1, processes=True, dashboard_address=":0",
                       silence_logs=logging.ERROR) as cluster, Client(cluster) as client):
        report = tune.tune(client, url, "load", settings, trials=TRIALS)
    study = optuna.load_study(study_name="load", storage=tune.normalise_storage_url(url))
    trials = study.get_trials(deepcopy=False)
    assert report.trials_run == TRIALS and report.complete + report.pruned == TRIALS and report.failed == 0
    assert sorted(t.number for t in trials) == list(range(TRIALS)) and all(t.state in tune.FINISHED for t in trials)
    assert len({tuple(sorted(t.params.items())) for t in trials}) == TRIALS
    spans = [(t.datetime_start.timestamp(), t.datetime_complete.timestamp()) for t in trials]
    assert max_overlap(spans) >= 3, "the trials should run side by side"


def test_correct_archive__200_scans_in_one_batch_all_accounted_for(
    tmp_path: Path, dask_cluster: DaskCluster, cluster_model: Path
) -> None:
    archive = tmp_path / "archive"
    out = tmp_path / "out"
    with Client(dask_cluster.address) as client:
        client.gather(client.map(write_small_scan, [archive] * SCANS, range(SCANS)))
        assert len(list(archive.glob("*.scan.zarr"))) == SCANS
        # 64 pixels a scan, too few to read their amplitude unit: given, V^2. The archive default output level:
        # accounting, not figures, is tested.
        options = CorrectionOptions(gate="all", amplitude_scale=1.0)
        outcomes = correct_archive([str(archive)], cluster_model, out, options, client, outputs="light")
    assert sorted(o.name for o in outcomes) == [f"s{i:03d}" for i in range(SCANS)]
    assert all(o.status == "corrected" and o.counts["corrected"] == 64 for o in outcomes)
    written = sorted(p.name for p in out.iterdir())
    assert written == [f"s{i:03d}" for i in range(SCANS)]
    assert all(json.loads((out / name / "metrics.json").read_text()) for name in written)
