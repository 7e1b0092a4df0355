"""mpi-lidar correct: a batch of scans, each with its outputs and report, and the batch's summary.

Its options beyond the scans, the model and the output directory are declared once, as the fields of
:class:`~mpi_lidar.correction.CorrectionOptions` and :class:`~mpi_lidar.workflows.batch_options.BatchOptions`
(the correction flow takes the same, by the same names).
"""

from __future__ import annotations

import sys
from pathlib import Path
from typing import TYPE_CHECKING

import click

from mpi_lidar.cli._declared import DeclaredCommand, declared_options
from mpi_lidar.terminal import Display, plural

if TYPE_CHECKING:
    from mpi_lidar.correction import ScanOutcome


def declared() -> list[click.Parameter]:
    """The options of every scan, then those of the batch."""
    from mpi_lidar.correction.options import USER_OPTIONS, CorrectionOptions
    from mpi_lidar.workflows.batch_options import BATCH_OPTIONS, BatchOptions

    return [*declared_options(CorrectionOptions, USER_OPTIONS), *declared_options(BatchOptions, BATCH_OPTIONS)]


@click.command(cls=DeclaredCommand, declared=declared)
@click.argument("scans", nargs=-1, required=True)
@click.option("--model", "model_dir", required=True, metavar="PATH|URL",
              help="Model directory, or its object-store URL (s3://bucket/models/m).")
@click.option("--out", "out_dir", required=True, metavar="PATH|URL",
              help="Output directory, or an object-store URL (s3://bucket/prefix).")
def correct(scans: tuple[str, ...], model_dir: str, out_dir: str, **given: object) -> None:
    """Correct scans (stores, directories or globs) in batch; one report per scan and a batch summary.

    \b
    Example:
      mpi-lidar correct 'archive/2026-11-*/*.scan.zarr' --model runs/model --out corrected --fail-on degraded

    Each scan ends corrected, unchanged (no pixel corrected), degraded (too many invalid pixels), unserved
    (the model cannot serve it: the reason says which command helps), skipped (already done) or failed. Exit 1
    when a scan failed, is unserved (unless --allow-unserved) or has a --fail-on status; 2 on a user error.
    """
    import time

    from mpi_lidar.workflows.batch_options import batch_options
    from mpi_lidar.workflows.correct_archive import correct_archive, expand_archive, failing_outcomes, failure_line
    from mpi_lidar.workflows.executor import InProcess, dask_executor
    from mpi_lidar.workflows.remote_outputs import write_summary

    options, batch = batch_options({**given, "model": model_dir})
    started = time.perf_counter()
    here = not batch.scheduler and not batch.workers
    total = len(expand_archive(list(scans)))

    def summarise(outcomes: list[ScanOutcome]) -> str:  # while the batch still holds out_dir
        return write_summary(outcomes, time.perf_counter() - started, out_dir)

    with Display() as display, display.step("correcting scans", total, announce=False) as advance:
        with InProcess() if here else dask_executor(batch.scheduler, batch.workers or 2) as executor:
            summaries: list[str] = []
            outcomes = correct_archive(list(scans), model_dir, out_dir, options, executor,
                                       on_scan=lambda outcome: advance(f"{outcome.name}: {outcome.status}"),
                                       outputs=batch.outputs.value, point_clouds=batch.point_cloud_formats(),
                                       on_done=lambda done: summaries.append(summarise(done)),
                                       **batch.point_cloud_placement(), replace_options=batch.replace_options)
    wall_s = time.perf_counter() - started
    print_batch(outcomes, wall_s, summaries[0])
    failing = failing_outcomes(outcomes, batch.fail_on, batch.allow_unserved)
    for outcome in failing:
        click.echo(f"error: {failure_line(outcome)}", err=True)
    if failing:
        sys.exit(1)


def print_batch(outcomes: list[ScanOutcome], wall_s: float, summary_dir: str | Path, width: int | None = None) -> None:
    """The batch on the terminal, in ``width`` columns (the terminal's; 80 piped): a line counting the statuses, a
    compact table (every scan's name and status in full, its invalid share and MAE where any has one, its notes as
    short codes), the codes' legend (each note cut to the width: whole in the summary's files) and where the summary
    is. The same figures as the summary's report (``mpi_lidar.reporting.batch_report``).
    """
    from mpi_lidar.correction import ScanStatus
    from mpi_lidar.correction.outcome import invalid_share
    from mpi_lidar.terminal import cut, fitted_table_lines, note_codes, terminal_width

    width = width or terminal_width()

    def change(metrics: dict[str, float]) -> str:
        raw, corrected = (metrics.get(key) if isinstance(metrics, dict) else None
                          for key in ("raw_mae_m", "corrected_mae_m"))
        if not (isinstance(raw, int | float) and isinstance(corrected, int | float)):
            return ""
        return f"{1e3 * raw:.2f} -> {1e3 * corrected:.2f}"

    notes = [[n for n in (f"{o.reason} ({o.kept_status})" if o.kept_status else o.reason, *o.notes) if n]
             for o in outcomes]
    codes, legend = note_codes(notes)
    rows = [(o.name, o.status, f"{100 * invalid_share(o.counts):.1f} %" if o.counts else "",
             change(o.metrics.get("whole map", {})), change(o.metrics.get("masked region", {})), code)
            for o, code in zip(outcomes, codes, strict=True)]
    labels = {ScanStatus.SKIPPED: "already done"}
    counted = ", ".join(f"{n} {labels.get(status, status.value)}" for status in ScanStatus
                        if (n := sum(o.status == status for o in outcomes)))
    click.echo(f"{plural(len(outcomes), 'scan')} in {wall_s:.1f} s" + (f": {counted}" if counted else ""))
    for line in fitted_table_lines(("scan", "status", "invalid", "MAE [mm]", "masked MAE [mm]", "notes"), rows, width,
                                   optional=("invalid", "MAE [mm]", "masked MAE [mm]")):
        click.echo(line)
    for code, note in legend:
        click.echo(cut(f"{code}: {note}", width))
    where = f"{str(summary_dir).rstrip('/')}/report.html"
    said = f"summary: {where} (every note in full)"
    click.echo(said if len(said) <= width else f"summary (every note in full):\n{where}")  # a path stays whole
