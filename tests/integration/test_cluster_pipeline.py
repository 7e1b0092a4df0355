"""The whole pipeline through the command line against a real cluster and a shared PostgreSQL study."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import optuna
import pytest
import zarr

from mpi_lidar.cli import feature_spec
from mpi_lidar.learning import tune
from tests.fast_trials import TUNE_ROWS, queue_fast_trials
from tests.integration.conftest import DaskCluster, database_url, run_cli, subprocess_env

pytestmark = pytest.mark.slow

SIMULATE = ("--samples", "1000", "--chunk-rows", "250", "--seed", "5")
SCENES = ("flat_wall", "corner")
PASSWORD = "Tr1cky-s3cret-pw"


def files_containing(root: Path, needle: str) -> list[Path]:
    return [p for p in root.rglob("*") if p.is_file() and needle.encode() in p.read_bytes()]


def test_cli_pipeline__runs_unchanged_on_dask_processes_and_postgresql(
    tmp_path: Path, dask_cluster: DaskCluster, pg_database: str
) -> None:
    """The local server trusts 127.0.0.1, so a password in the URL is accepted, and must never show.

    Tuning gets the URL with ``--storage``, training from ``MPI_LIDAR_STORAGE_URL``.
    """
    cluster = ("--scheduler", dask_cluster.address)
    storage = database_url(pg_database, PASSWORD)
    data = tmp_path / "dataset.zarr"

    run_cli("simulate", "--out", str(data), *SIMULATE, *cluster)
    assert zarr.open_group(str(data), mode="r")["chunk_done"][:].all()

    # The study `tune` makes (same settings: it loads this one), one queued trial per trial: parameters that
    # stop early after tens of boosting rounds, where the sampler's first draws may take up to 1,000.
    queued = tune.open_study(storage, "it", tune.TuneSettings(str(data), feature_spec(data, None, None),
                                                              tune_rows=TUNE_ROWS))
    queue_fast_trials(queued, 2)
    tuned = run_cli("tune", "--data", str(data), "--storage", storage, "--study", "it", "--trials", "2",
                    "--tune-rows", str(TUNE_ROWS), *cluster)
    assert "2 trials run" in tuned.stdout and f"postgres:***@127.0.0.1:5432/{pg_database}" in tuned.stdout
    study = optuna.load_study(study_name="it", storage=tune.normalise_storage_url(storage))
    trials = study.get_trials(deepcopy=False)
    assert sorted(t.number for t in trials) == [0, 1]
    assert all(t.state in tune.FINISHED for t in trials)

    model = tmp_path / "model"
    trained = run_cli("train", "--data", str(data), "--out", str(model), "--study", "it", *cluster,
                      env=subprocess_env(MPI_LIDAR_STORAGE_URL=storage))
    card = json.loads((model / "card.json").read_text())
    assert card["training"]["dask_workers"] == 2
    assert card["params"]["max_depth"] == study.best_trial.params["max_depth"]

    scans = tmp_path / "scans"
    run_cli("render-scenes", "--out", str(scans), *[arg for name in SCENES for arg in ("--scene", name)])
    out = tmp_path / "corrected"
    run_cli("correct", str(scans), "--model", str(model), "--out", str(out), "--outputs", "full", *cluster)
    outputs = sorted(p for p in out.iterdir() if p.is_dir() and p.name != "summary")  # not the batch's plotly.js
    assert len(outputs) == len(SCENES)
    for output in outputs:
        depth = zarr.open_group(str(output / "corrected.zarr"), mode="r")["corrected_depth"][:]
        assert depth.shape == (96, 128) and np.isfinite(depth).mean() > 0.9
        assert (output / "report.html").is_file() and (output / "corrected.ply").is_file()
    assert "1 corrected, 1 unchanged, 0 degraded, 0 unserved, 0 already done, 0 failed" in (
        out / "summary" / "report.md").read_text()  # the corner is corrected, the flat wall left as measured
    assert not (tmp_path / "optuna.db").exists()
    assert all(PASSWORD not in r.stdout + r.stderr for r in (tuned, trained))
    assert files_containing(tmp_path, PASSWORD) == []
