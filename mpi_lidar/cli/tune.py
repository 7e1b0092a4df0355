"""mpi-lidar tune: the Optuna study of the XGBoost model's parameters."""

from __future__ import annotations

import click

from mpi_lidar.cli._common import cluster_options, feature_spec, model_options
from mpi_lidar.cli._declared import bounded
from mpi_lidar.terminal import Display, plural
from mpi_lidar.workflows.job_options import Trials, TuneRows


@click.command()
@click.option("--data", required=True, metavar="PATH|URL",
              help="Dataset store (.zarr): a path or a URL (s3://, gs://, az://).")
@click.option("--storage", help="Optuna storage URL (default: $MPI_LIDAR_STORAGE_URL, else sqlite file optuna.db "
                                "beside a dataset on disk; a dataset in a bucket needs one).")
@click.option("--study", "study_name", default="xgboost", show_default=True, help="Study name in the storage.")
@click.option("--trials", type=bounded(Trials), default=30, show_default=True,
              help="Finished trials the study should hold; a re-run resumes or extends it.")
@click.option("--tune-rows", type=bounded(TuneRows), default=100_000, show_default=True,
              help="Train rows each trial learns from.")
@model_options
@cluster_options
def tune(data: str, storage: str | None, study_name: str, trials: int, tune_rows: int, feature_set: str | None,
         target_mode: str | None, geometric: bool | None, workers: int, scheduler: str | None) -> None:
    """Tune XGBoost with Optuna TPE, trials running in parallel on Dask workers.

    \b
    Example:
      mpi-lidar tune --data runs/d.zarr --trials 30 --storage postgresql://user@db-host/optuna
    """
    from mpi_lidar.learning import tune as tuning
    from mpi_lidar.workflows.cluster import dask_client

    storage = tuning.storage_url(storage, data)
    settings = tuning.TuneSettings(data, feature_spec(data, feature_set, target_mode, geometric),
                                   tune_rows=tune_rows)
    study = tuning.open_study(storage, study_name, settings)
    todo = max(0, trials - tuning.count(study, *tuning.FINISHED))
    with Display() as display, dask_client(scheduler, workers) as client, display.step("trials", todo) as advance:
        report = tuning.tune(client, storage, study_name, settings, trials, on_trial=lambda _n: advance())
    click.echo(f"study {study_name!r} in {tuning.masked(storage)}: {plural(report.trials_run, 'trial')} run in "
               f"{report.wall_s:.1f} s; {report.complete} complete, {report.pruned} pruned, {report.failed} failed")
    if report.best_value_m is not None:
        click.echo(f"best validation MAE {1e3 * report.best_value_m:.3f} mm with {report.best_params}")
