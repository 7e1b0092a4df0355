"""mpi-lidar evaluate: a model's metrics on a dataset split, and their report."""

from __future__ import annotations

import click

from mpi_lidar.terminal import Display, print_table


@click.command()
@click.option("--data", required=True, metavar="PATH|URL",
              help="Dataset store (.zarr): a path or a URL (s3://, gs://, az://).")
@click.option("--model", "model_dir", required=True, metavar="PATH|URL",
              help="Model directory, or its object-store URL (s3://bucket/models/m).")
@click.option("--out", "--report", "report_dir", required=True, metavar="PATH|URL",
              help="Report directory, or its object-store URL (s3://bucket/reports/r); --report is the older name.")
@click.option("--split", type=click.Choice(["test", "train"]), default="test", show_default=True)
def evaluate(data: str, model_dir: str, report_dir: str, split: str) -> None:
    """Evaluate a model on a dataset split: metrics table, error histogram, report files.

    \b
    Example:
      mpi-lidar evaluate --data runs/d.zarr --model runs/model --out runs/report
    """
    from mpi_lidar.reporting.report import Table
    from mpi_lidar.workflows.pipeline import evaluate_to_report

    with Display() as display, display.step(f"evaluating on the {split} split"):
        _, report = evaluate_to_report(data, model_dir, report_dir, split)
    metrics = next(block for block in report.blocks if isinstance(block, Table))
    print_table(metrics.headers, metrics.rows)
    click.echo(f"report written to {report_dir}")
