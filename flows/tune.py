"""Prefect flow: tune XGBoost with Optuna TPE, trials running as Dask tasks on a shared RDB study.

:func:`mpi_lidar.learning.tune.tune` submits the trials to the cluster itself; this flow wraps it in one task and
publishes the best trial, the trial table and the optimisation-history and importance plots.
"""

from __future__ import annotations

from pathlib import Path

from prefect import flow, task
from prefect.artifacts import create_markdown_artifact
from prefect.cache_policies import NO_CACHE

from mpi_lidar.learning import tune
from mpi_lidar.learning.features import DEFAULT_FEATURE_SET, DEFAULT_GEOMETRIC, DEFAULT_TARGET_MODE, FeatureSpec
from mpi_lidar.reporting.report import write_report
from mpi_lidar.reporting.tuning_report import tuning_report
from mpi_lidar.simulation import dataset
from mpi_lidar.workflows.cluster import dask_client

TUNING_ARTIFACT_KEY = "tuning-study"


@task(name="run-trials", cache_policy=NO_CACHE)
def run_trials_task(storage: str, study: str, settings: tune.TuneSettings, trials: int, workers: int,
                    scheduler: str | None) -> tune.TuneReport:
    with dask_client(scheduler, workers) as client:
        return tune.tune(client, storage, study, settings, trials)


@task(name="publish-study", cache_policy=NO_CACHE)
def publish_study_task(storage: str, study: str, report_dir: str) -> str:
    """The study's report as files (with its plots) and as a markdown artifact; the storage is masked."""
    report, figures = tuning_report(tune.load_existing_study(storage, study), tune.masked(storage))
    write_report(report, report_dir, figures)
    markdown = report.markdown().replace("](", f"]({report_dir}/")
    create_markdown_artifact(markdown=markdown, key=TUNING_ARTIFACT_KEY, description=f"Optuna study {study}")
    return markdown


@flow(name="tune")
def tune_flow(data: str, storage: str | None = None, study: str = "xgboost", trials: int = tune.DEFAULT_TRIALS,
              tune_rows: int = tune.DEFAULT_TUNE_ROWS, feature_set: str | None = None, target: str | None = None,
              geometric: bool = DEFAULT_GEOMETRIC, workers: int = 2, scheduler: str | None = None,
              report_dir: str | None = None) -> dict[str, object]:
    """Run the study to ``trials`` finished trials and publish it (report in ``<data dir>/tuning`` by default)."""
    storage = tune.storage_url(storage, data)
    spec = FeatureSpec(dataset.dataset_info(data).frequencies_hz, feature_set or DEFAULT_FEATURE_SET,
                       target or DEFAULT_TARGET_MODE, geometric)
    settings = tune.TuneSettings(data, spec, tune_rows=tune_rows)
    result = run_trials_task(storage, study, settings, trials, workers, scheduler)
    report_dir = report_dir or str(Path(data).parent / "tuning")
    publish_study_task(storage, study, report_dir)
    return {"trials_run": result.trials_run, "complete": result.complete, "pruned": result.pruned,
            "failed": result.failed, "best_value_m": result.best_value_m, "best_params": result.best_params,
            "wall_s": result.wall_s, "report_dir": report_dir}
