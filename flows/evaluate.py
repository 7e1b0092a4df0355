"""Prefect flows: evaluate a model on a dataset split, and the paper's Table II with its baselines."""

from __future__ import annotations

from typing import Literal

from prefect import flow, task
from prefect.artifacts import create_markdown_artifact
from prefect.cache_policies import NO_CACHE

from mpi_lidar.learning.baselines import table2
from mpi_lidar.learning.evaluate import Evaluation
from mpi_lidar.reporting.report import Report, write_report_to
from mpi_lidar.reporting.table2 import table2_report
from mpi_lidar.workflows.job_options import BaselineRows, Trials
from mpi_lidar.workflows.pipeline import evaluate_to_report

Split = Literal["test", "train"]  # the dataset splits a model is evaluated on, as mpi-lidar evaluate --split
EVALUATION_ARTIFACT_KEY = "evaluation"
TABLE2_ARTIFACT_KEY = "table-2"


def _publish(report: Report, report_dir: str, key: str) -> str:
    markdown = report.markdown().replace("](", f"]({report_dir}/")
    create_markdown_artifact(markdown=markdown, key=key, description=report.title)
    return markdown


@task(name="evaluate-model", cache_policy=NO_CACHE)
def evaluate_task(data: str, model: str, report_dir: str, split: str) -> tuple[Evaluation, str]:
    """Metrics of raw, weighted and corrected depth, and the error histogram before and after correction.

    The report is written as ``mpi-lidar evaluate`` writes it, and published; returns the evaluation and
    the published markdown.
    """
    evaluation, report = evaluate_to_report(data, model, report_dir, split)
    return evaluation, _publish(report, report_dir, EVALUATION_ARTIFACT_KEY)


@task(name="table-2", cache_policy=NO_CACHE)
def table2_task(data: str, model: str | None, report_dir: str, trials: int, train_rows: int, svm_rows: int) -> str:
    report, figures = table2_report(table2(data, model, trials=trials, train_rows=train_rows, svm_rows=svm_rows))
    write_report_to(report, report_dir, figures)
    return _publish(report, report_dir, TABLE2_ARTIFACT_KEY)


@flow(name="evaluate")
def evaluate_flow(data: str, model: str, report: str, split: Split = "test") -> str:
    """``mpi-lidar evaluate`` as a flow (``report`` is ``--out``); returns the published markdown."""
    return evaluate_task(data, model, report, split)[1]


@flow(name="table-2")
def table2_flow(data: str, report: str, model: str | None = None, trials: Trials = 10,
                train_rows: BaselineRows = 100_000, svm_rows: BaselineRows = 20_000) -> str:
    """``mpi-lidar table2`` as a flow (``report`` is ``--out``); returns the published markdown."""
    return table2_task(data, model, report, trials, train_rows, svm_rows)
