"""The report of a batch: status counts and a chart, one table over its scans (problems first), the notes and
sources collapsed below it, what made it, and the summary written beside their outputs."""

from __future__ import annotations

import json
import math
import os
from pathlib import Path

from markupsafe import Markup

from mpi_lidar.correction import CorrectionOptions, Flag, ScanOutcome, ScanStatus
from mpi_lidar.correction.outcome import invalid_share
from mpi_lidar.reporting.report import Block, Embed, Report, Table, write_report

# Valid pixels left as measured because the gate found no need for a correction.
GATED_OUT = tuple(flag.name.lower() for flag in (Flag.NOT_NEEDED, Flag.NO_MULTIPATH, Flag.UNCALIBRATED))
# Statuses an engineer must look at: listed first and marked.
PROBLEMS = (ScanStatus.FAILED, ScanStatus.UNSERVED, ScanStatus.DEGRADED)
PROBLEM_MARK = "⚠ "
STATUS_COLOURS = {ScanStatus.CORRECTED: "#2e86de", ScanStatus.UNCHANGED: "#10ac84", ScanStatus.SKIPPED: "#c8d6e5",
                  ScanStatus.DEGRADED: "#ff9f43", ScanStatus.UNSERVED: "#a55eea", ScanStatus.FAILED: "#ee5253"}
STATUS_LABELS = {ScanStatus.SKIPPED: "already done"}
def batch_report(outcomes: list[ScanOutcome], wall_s: float, summary_dir: Path | None = None) -> Report:
    """The batch at a glance: a line counting every status and a bar of them; one table of the scans, failed,
    unserved and degraded ones first and marked (⚠), with only the columns some scan fills (name, status,
    gated-out and invalid shares, MAE before/after on the whole map and the mask, seconds, notes as codes); then
    the notes and source paths, collapsed, and the model, options and sensor profile the scans' outputs record.

    Gated out: valid pixels left alone because the gate found no need (no multipath potential, or not needed by a
    pixel-wise gate), as a share of all pixels. Invalid: pixels flagged invalid, as a share of all pixels. A
    skipped scan shows the numbers of its existing outputs, and its notes say the status those earned; a scan
    without a valid pixel says so in its notes. With ``summary_dir`` (where the summary is written) the second
    column links each scan's own report.
    """
    ordered = sorted(outcomes, key=lambda o: (o.status not in PROBLEMS, PROBLEMS.index(o.status)
                                              if o.status in PROBLEMS else 0))
    notes = [_notes(o) for o in ordered]
    codes = _codes(notes)
    rows = []
    for o, code in zip(ordered, codes, strict=True):
        total = max(sum(o.counts.values()), 1)
        gated = sum(o.counts.get(name, 0) for name in GATED_OUT)
        whole, masked = o.metrics.get("whole map", {}), o.metrics.get("masked region", {})
        status = (PROBLEM_MARK if o.status in PROBLEMS else "") + str(o.status)
        cells = tuple(_cell(c) for c in (
            o.name, status, f"{100 * gated / total:.1f} %" if o.counts else "",
            f"{100 * invalid_share(o.counts):.1f} %" if o.counts else "", _mm(whole, "raw_mae_m"),
            _mm(whole, "corrected_mae_m"), _mm(masked, "raw_mae_m"), _mm(masked, "corrected_mae_m"),
            f"{o.seconds:.2f}", code))
        rows.append(cells[:1] + _report_link(o, summary_dir) + cells[1:])
    headers = ("scan", *(("report",) if summary_dir is not None else ()), "status", "gated out", "invalid",
               "raw MAE [mm]", "corrected MAE [mm]", "masked raw MAE [mm]", "masked corrected MAE [mm]", "seconds",
               "notes")
    filled = [i for i, h in enumerate(headers) if h in ("scan", "status") or any(row[i] for row in rows)]
    table = Table(tuple(headers[i] for i in filled), tuple(tuple(row[i] for i in filled) for row in rows))
    counted = ", ".join(f"{sum(o.status == status for o in outcomes)} {STATUS_LABELS.get(status, status.value)}"
                        for status in ScanStatus)
    summary = f"{len(outcomes)} scan{'' if len(outcomes) == 1 else 's'} in {wall_s:.1f} s: {counted}."
    blocks: list[Block] = [summary, _status_chart(outcomes), table, _notes_block(ordered, notes, codes)]
    blocks += _provenance(outcomes)
    return Report(title="Batch correction", blocks=blocks,
                  data={"wall_s": wall_s, "scans": [o.__dict__ for o in outcomes]})


def _notes(outcome: ScanOutcome) -> list[str]:
    """A scan's notes in full: why it failed or was skipped (with the status kept), no valid pixel, the others."""
    reason = f"{outcome.reason} ({outcome.kept_status})" if outcome.kept_status else outcome.reason
    first = ["no valid pixel"] if outcome.counts and invalid_share(outcome.counts) >= 1.0 else []
    return [n for n in (*first, reason, *outcome.notes) if n]


def _codes(notes: list[list[str]]) -> list[str]:
    """Short codes of each scan's notes (``n1 n2``), one per distinct note, numbered in order of first use."""
    known: dict[str, str] = {}
    for row in notes:
        for note in row:
            known.setdefault(note, f"n{len(known) + 1}")
    return [" ".join(known[n] for n in dict.fromkeys(row)) for row in notes]


def _status_chart(outcomes: list[ScanOutcome]) -> Embed:
    """A bar of the batch's statuses, one segment per status as wide as its share, with its count."""
    counts = [(s, sum(o.status == s for o in outcomes)) for s in ScanStatus]
    total = max(len(outcomes), 1)
    segments = Markup("").join(
        Markup('<span title="{n} {label}" style="flex:{n} 1 0;background:{colour};color:#fff;padding:.2em .4em;'
               'min-width:2.5em;white-space:nowrap;overflow:hidden">{n} {label}</span>').format(
            n=n, label=STATUS_LABELS.get(s, s.value), colour=STATUS_COLOURS[s])
        for s, n in counts if n)
    markup = Markup('<div class="status-chart" role="img" aria-label="scans per status" '
                    'style="display:flex;gap:2px;max-width:100%;margin:.5em 0;font-size:.9em">{}</div>').format(
        segments)
    fallback = ", ".join(f"{n} {STATUS_LABELS.get(s, s.value)} ({100 * n / total:.0f} %)" for s, n in counts if n)
    return Embed(str(markup), fallback=f"Statuses: {fallback}.")


def _notes_block(ordered: list[ScanOutcome], notes: list[list[str]], codes: list[str]) -> Embed:
    """The notes in full, each once under its code, and every scan's source path, collapsed under one summary."""
    legend: dict[str, str] = {}
    for row, code in zip(notes, codes, strict=True):
        legend.update(zip(code.split(), dict.fromkeys(row), strict=True))
    items = Markup("").join(Markup("<dt>{}</dt><dd>{}</dd>").format(code, note) for code, note in legend.items())
    sources = Markup("").join(Markup("<dt>{}</dt><dd><code>{}</code></dd>").format(o.name, o.source)
                              for o in ordered)
    markup = Markup('<details><summary>Notes ({}) and source paths</summary><dl>{}</dl><h3>Sources</h3><dl>{}</dl>'
                    '</details>').format(len(legend), items, sources)
    text = "\n".join([*(f"- {code}: {note}" for code, note in legend.items()),
                      *(f"- {o.name}: `{o.source}`" for o in ordered)])
    return Embed(str(markup), fallback=f"Notes and sources:\n\n{text}" if text else "No notes.")


def _provenance(outcomes: list[ScanOutcome]) -> list[Block]:
    """What made the scans' outputs, as their ``corrected.zarr`` records it: the model's and options' hashes, the
    options that differ from the defaults, the sensor profile and the output level; one line per combination."""
    seen: dict[str, list[str]] = {}
    defaults = CorrectionOptions().model_dump()
    for o in outcomes:
        attrs = _store_attributes(o.output)
        if not attrs:
            continue
        recorded = attrs.get("options")
        options: dict[str, object] = recorded if isinstance(recorded, dict) else {}
        changed = ", ".join(f"{k}={v}" for k, v in sorted(options.items())
                            if k in defaults and v != defaults[k] and k != "sensor_profile_sha256") or "defaults"
        profile = options.get("sensor_profile_sha256")
        model, hashed = (str(attrs.get(key, "?"))[:12] for key in ("model_sha256", "options_sha256"))
        sensor = f"`{str(profile)[:12]}`" if profile else "none (the default sensor)"
        level = attrs.get("outputs", "?")
        line = f"model `{model}`, options `{hashed}` ({changed}), sensor profile {sensor}, outputs {level}"
        seen.setdefault(line, []).append(o.name)
    if not seen:
        return []
    return ["Made by: " + "; ".join(f"{line} ({len(names)} scan{'' if len(names) == 1 else 's'})"
                                    for line, names in seen.items()) + "."]


def _store_attributes(output: str) -> dict[str, object]:
    """The attributes of a scan's ``corrected.zarr`` where its outputs are a local folder (empty otherwise)."""
    path = Path(output) / "corrected.zarr" / "zarr.json" if output and "://" not in output else None
    try:
        attrs = json.loads(path.read_text()).get("attributes", {}) if path is not None else {}
    except (OSError, ValueError):
        return {}
    return attrs if isinstance(attrs, dict) else {}


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
