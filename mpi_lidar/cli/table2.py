"""mpi-lidar table2: the paper's Table II, the XGBoost model beside its baselines."""

from __future__ import annotations

from pathlib import Path

import click

from mpi_lidar.cli._declared import bounded
from mpi_lidar.terminal import Display, print_table
from mpi_lidar.workflows.job_options import BaselineRows, Trials


@click.command()
@click.option("--data", type=click.Path(path_type=Path), required=True, help="Dataset store (.zarr).")
@click.option("--out", "--report", "report_dir", required=True, metavar="PATH|URL",
              help="Report directory, or its object-store URL (s3://bucket/reports/r); --report is the older name.")
@click.option("--model", "model_dir", type=click.Path(path_type=Path), help="XGBoost model directory for its row.")
@click.option("--trials", type=bounded(Trials), default=10, show_default=True, help="TPE trials per baseline.")
@click.option("--train-rows", type=bounded(BaselineRows), default=100_000, show_default=True,
              help="Train rows the scikit-learn baselines fit on.")
@click.option("--svm-rows", type=bounded(BaselineRows), default=20_000, show_default=True)
def table2(data: Path, report_dir: str, model_dir: Path | None, trials: int, train_rows: int, svm_rows: int) -> None:
    """The paper's Table II: KNN, RF, SVM, DNN and XGBoost against raw and weighted depth.

    \b
    Example:
      mpi-lidar table2 --data runs/paper/dataset.zarr --model runs/paper/model --out runs/table2
    """
    from mpi_lidar.learning.baselines import table2 as make_table2
    from mpi_lidar.reporting.report import write_report_to
    from mpi_lidar.reporting.table2 import table2_report, table2_table

    with Display() as display, display.step("baselines", 4) as advance:
        result = make_table2(data, model_dir, train_rows=train_rows, trials=trials, svm_rows=svm_rows,
                             on_row=lambda _row: advance())
    report, figures = table2_report(result)
    write_report_to(report, report_dir, figures)
    table = table2_table(result)
    print_table(table.headers, table.rows)
    click.echo(f"report written to {report_dir}")
