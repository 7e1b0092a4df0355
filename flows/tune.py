"""Prefect flow: tune XGBoost with Optuna TPE, trials running as Dask tasks on a shared RDB study.

:func:`mpi_lidar.learning.tune.tune` submits the trials to the cluster itself; this flow wraps it in one task and
publishes the best trial, the trial table and the optimisation-history and importance plots.

Prefect stores a flow run's parameters in its database and shows them in the UI, so the storage's password is
never a parameter: a ``storage`` that carries one is refused (and masked in what Prefect records of the call).
The password reaches the flow from the machine that runs it: ``MPI_LIDAR_STORAGE_URL`` (leave ``storage`` out),
PostgreSQL's own ``PGPASSWORD`` or ``~/.pgpass`` (give ``storage`` without a password), or a Prefect Secret
block holding the whole URL, named by ``storage_secret``.
"""

from __future__ import annotations

from pathlib import Path
from typing import cast

from prefect import Flow, task
from prefect.artifacts import create_markdown_artifact
from prefect.cache_policies import NO_CACHE

from mpi_lidar.errors import ConfigError
from mpi_lidar.learning import tune
from mpi_lidar.learning.features import DEFAULT_FEATURE_SET, DEFAULT_GEOMETRIC, DEFAULT_TARGET_MODE, FeatureSpec
from mpi_lidar.redact import carries_secret, install_log_redaction, redact
from mpi_lidar.reporting.report import write_report_to
from mpi_lidar.reporting.tuning_report import tuning_report
from mpi_lidar.simulation import dataset
from mpi_lidar.workflows.cluster import dask_client
from mpi_lidar.workflows.job_options import Trials, TuneRows, Workers

TUNING_ARTIFACT_KEY = "tuning-study"
WHERE_SECRETS_COME_FROM = (f"leave storage out and set {tune.STORAGE_URL_VARIABLE} where the flow runs, give the URL "
                           "without its password (PostgreSQL then reads PGPASSWORD or ~/.pgpass there), or save "
                           "the URL in a Prefect Secret block and name it in storage_secret")


def flow_storage(storage: str | None, storage_secret: str | None, data: str) -> str:
    """The study storage of a flow run: ``storage`` (refused if it carries a password), else the Prefect Secret
    block ``storage_secret``, else ``$MPI_LIDAR_STORAGE_URL``, else the SQLite file beside the dataset."""
    if storage is not None and carries_secret(storage):
        raise ConfigError(f"the tune flow's storage parameter carries a password ({redact(storage)}), and Prefect "
                          f"stores and shows flow-run parameters in clear; {WHERE_SECRETS_COME_FROM}")
    if storage is None and storage_secret:
        from prefect.blocks.system import Secret

        try:
            secret = cast(Secret, Secret.load(storage_secret))
        except ValueError as exc:  # no such block
            raise ConfigError(f"Prefect Secret block {storage_secret!r} cannot be loaded ({redact(str(exc))}); "
                              "save the storage URL with prefect.blocks.system.Secret(value=URL).save(NAME)") from None
        storage = str(secret.get())
    return tune.storage_url(storage, data)


class SecretsMaskedFlow(Flow):
    """A flow whose recorded parameters have every password masked (:func:`mpi_lidar.redact.redact`).

    Prefect records a flow run's parameters as the caller passes them, before the flow's code runs; this keeps
    a password out of that record, and the flow then refuses the parameter."""

    def serialize_parameters(self, parameters: dict[str, object]) -> dict[str, object]:
        serialized = super().serialize_parameters(parameters)
        return {key: redact(value) if isinstance(value, str) else value for key, value in serialized.items()}


@task(name="run-trials", cache_policy=NO_CACHE)
def run_trials_task(storage: str, study: str, settings: tune.TuneSettings, trials: int, workers: int,
                    scheduler: str | None) -> tune.TuneReport:
    with dask_client(scheduler, workers) as client:
        return tune.tune(client, storage, study, settings, trials)


@task(name="publish-study", cache_policy=NO_CACHE)
def publish_study_task(storage: str, study: str, report_dir: str) -> str:
    """The study's report as files (with its plots) and as a markdown artifact; the storage is masked."""
    report, figures = tuning_report(tune.load_existing_study(storage, study), tune.masked(storage))
    write_report_to(report, report_dir, figures)
    markdown = report.markdown().replace("](", f"]({report_dir}/")
    create_markdown_artifact(markdown=markdown, key=TUNING_ARTIFACT_KEY, description=f"Optuna study {study}")
    return markdown


def tune_flow(data: str, storage: str | None = None, study: str = "xgboost", trials: Trials = tune.DEFAULT_TRIALS,
              tune_rows: TuneRows = tune.DEFAULT_TUNE_ROWS, feature_set: str | None = None, target: str | None = None,
              geometric: bool = DEFAULT_GEOMETRIC, workers: Workers = 2, scheduler: str | None = None,
              report_dir: str | None = None, storage_secret: str | None = None) -> dict[str, object]:
    """Run the study to ``trials`` finished trials and publish it (report in ``<data dir>/tuning`` by default).

    ``storage`` must not carry a password (see the module's docstring); ``storage_secret`` names a Prefect Secret
    block that holds the storage URL, password included, used where ``storage`` is left out.
    """
    install_log_redaction()
    storage = flow_storage(storage, storage_secret, data)
    spec = FeatureSpec(dataset.dataset_info(data).frequencies_hz, feature_set or DEFAULT_FEATURE_SET,
                       target or DEFAULT_TARGET_MODE, geometric)
    settings = tune.TuneSettings(data, spec, tune_rows=tune_rows)
    result = run_trials_task(storage, study, settings, trials, workers, scheduler)
    report_dir = report_dir or str(Path(data).parent / "tuning")
    publish_study_task(storage, study, report_dir)
    return {"trials_run": result.trials_run, "complete": result.complete, "pruned": result.pruned,
            "failed": result.failed, "best_value_m": result.best_value_m, "best_params": result.best_params,
            "wall_s": result.wall_s, "report_dir": report_dir}


# The flow keeps its function's name: a deployment's entrypoint is flows/tune.py:tune_flow.
tune_flow = SecretsMaskedFlow(tune_flow, name="tune")
