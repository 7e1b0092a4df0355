"""The report of a batch: one table over its scans, and the summary written beside their outputs."""

from __future__ import annotations

import math
import os
from pathlib import Path

from mpi_lidar.correction import Flag, ScanOutcome, ScanStatus
from mpi_lidar.correction.outcome import invalid_share
from mpi_lidar.reporting.report import Report, Table, write_report

# Valid pixels left as measured because the gate found no need for a correction.
GATED_OUT = tuple(flag.name.lower() for flag in (Flag.NOT_NEEDED, Flag.NO_MULTIPATH, Flag.UNCALIBRATED))


def batch_report(outcomes: list[ScanOutcome], wall_s: float, summary_dir: Path | None = None) -> Report:
    """One table over the batch: per scan its name, status, gated-out and invalid shares, MAE before/after on
    the whole map and the mask, notes and source path; above it a line counting every status.

    Gated out: valid pixels left as measured because the gate found no need (no multipath potential, or
    not needed by a pixel-wise gate), as a share of all pixels. Invalid: pixels flagged not finite, no
    return, saturated or inconsistent, as a share of all pixels. A skipped scan shows the numbers of its
    existing outputs, and its notes say the status those earned; a scan without a valid pixel says so in its
    notes (its errors are left empty). With ``summary_dir`` (where the summary is
    written) the second column links each scan's own report (in sight on a narrow page).
    """
    rows = []
    for o in outcomes:
        total = max(sum(o.counts.values()), 1)
        gated = sum(o.counts.get(name, 0) for name in GATED_OUT)
        not_needed = f"{100 * gated / total:.1f} %" if o.counts else ""
        invalid = f"{100 * invalid_share(o.counts):.1f} %" if o.counts else ""
        whole, masked = o.metrics.get("whole map", {}), o.metrics.get("masked region", {})
        reason = f"{o.reason} ({o.kept_status})" if o.kept_status else o.reason
        if o.counts and invalid_share(o.counts) >= 1.0:
            reason = "; ".join(n for n in ("no valid pixel", reason) if n)
        cells = tuple(_cell(c) for c in (
            o.name, o.status, not_needed, invalid, _mm(whole, "raw_mae_m"), _mm(whole, "corrected_mae_m"),
            _mm(masked, "raw_mae_m"), _mm(masked, "corrected_mae_m"), f"{o.seconds:.2f}",
            "; ".join(n for n in (reason, *o.notes) if n), o.source))
        rows.append(cells[:1] + _report_link(o, summary_dir) + cells[1:])
    headers = ("scan", *(("report",) if summary_dir is not None else ()), "status", "gated out", "invalid",
               "raw MAE [mm]", "corrected MAE [mm]", "masked raw MAE [mm]", "masked corrected MAE [mm]", "seconds",
               "notes", "source")
    table = Table(headers, tuple(rows))
    labels = {ScanStatus.SKIPPED: "already done"}
    counted = ", ".join(f"{sum(o.status == status for o in outcomes)} {labels.get(status, status.value)}"
                        for status in ScanStatus)
    summary = f"{len(outcomes)} scan{'' if len(outcomes) == 1 else 's'} in {wall_s:.1f} s: {counted}."
    return Report(title="Batch correction", blocks=[summary, table],
                  data={"wall_s": wall_s, "scans": [o.__dict__ for o in outcomes]})


def _cell(text: object) -> str:
    """One table cell of plain text: one line, no ``|`` that would split a markdown row, no markup."""
    text = " ".join(str(text).splitlines())
    for special in ("\\", "|", "*", "[", "]", "`"):
        text = text.replace(special, "\\" + special)
    return text


def _report_link(outcome: ScanOutcome, summary_dir: Path | None) -> tuple[str, ...]:
    """The link cell from the summary to the scan's own report, where one was written."""
    if summary_dir is None:
        return ()
    report = Path(outcome.output) / "report.html" if outcome.output else None
    if report is None or not report.is_file():
        return ("",)
    return (f"[report]({Path(os.path.relpath(report, summary_dir)).as_posix()})",)


def _mm(metrics: dict[str, float], key: str) -> str:
    value = metrics.get(key) if isinstance(metrics, dict) else None
    return f"{1e3 * value:.3f}" if isinstance(value, int | float) and math.isfinite(value) else ""


def write_batch_report(outcomes: list[ScanOutcome], wall_s: float, out_dir: str | Path) -> Path:
    """The batch summary into ``<out_dir>/summary/`` (a name no scan's outputs take, see correct_archive)."""
    summary_dir = Path(out_dir) / "summary"
    return write_report(batch_report(outcomes, wall_s, summary_dir), summary_dir, {})
