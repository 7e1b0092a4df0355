"""Report pieces written as files: markdown tables and PNG figures (written atomically).

Figures are :class:`matplotlib.figure.Figure` objects of their own, never pyplot's: importing this module
or writing a report changes nothing of pyplot's global state (its backend, a user's open figures), and
``Figure.savefig`` renders PNGs with the Agg canvas whatever backend pyplot uses.
"""

from __future__ import annotations

import json
import re
from dataclasses import dataclass, field
from functools import lru_cache
from pathlib import Path
from typing import TYPE_CHECKING, Protocol, cast

import jinja2
import numpy as np
from markdown_it import MarkdownIt
from markupsafe import Markup

from mpi_lidar.learning.evaluate import Evaluation
from mpi_lidar.learning.model import ModelCard
from mpi_lidar.locations import is_url, location
from mpi_lidar.simulation import dataset
from mpi_lidar.storage.atomic import atomic_path

if TYPE_CHECKING:
    from matplotlib.figure import Figure  # imported where a figure is drawn: matplotlib costs 0.35 s


class GenerationRun(Protocol):
    """What a generation run reports (:class:`mpi_lidar.workflows.generate.GenerationReport`, a layer above)."""

    @property
    def chunks_written(self) -> int: ...
    @property
    def chunks_skipped(self) -> int: ...
    @property
    def rows_written(self) -> int: ...
    @property
    def wall_s(self) -> float: ...
    @property
    def rows_per_s(self) -> float: ...


def generation_markdown(summary: dataset.DatasetSummary, run: GenerationRun, workers: str) -> str:
    """The dataset-generation summary: raw errors per frequency, then wall time and throughput."""
    lines = [
        summary.to_markdown(),
        "",
        "| run | value |",
        "|---|---|",
        f"| chunks written / skipped | {run.chunks_written} / {run.chunks_skipped} |",
        f"| rows written | {run.rows_written:,} |",
        f"| wall time | {run.wall_s:.2f} s |",
        f"| throughput | {run.rows_per_s:,.0f} rows/s |",
        f"| workers | {workers} |",
    ]
    return "\n".join(lines)


def save_figure(fig: Figure, path: str | Path) -> Path:
    """Save a figure through a temporary file and a rename, so a reader never sees half a PNG."""
    path = Path(path)
    with atomic_path(path, replace=True, what="figure") as staging:
        fig.savefig(staging, dpi=120, bbox_inches="tight", format="png")
    return path


def depth_error_histogram(store: str | Path, png: str | Path, frequency_index: int = -1) -> Path:
    """Histogram of the absolute raw depth error at one frequency (the paper's Fig. 5: 31.25 MHz)."""
    group = dataset.open_store(store)
    frequencies_hz = cast("list[float]", group.attrs["frequencies_hz"])
    frequency = frequencies_hz[frequency_index]
    column = frequency_index % len(frequencies_hz)
    # Chunk by chunk, each checked against its fingerprint: a damaged store is refused, never plotted.
    arrays = dataset.read_verified(store, ("features", "target"),
                                   on_chunk=lambda chunk: {"features": chunk["features"][:, column:column + 1],
                                                           "target": chunk["target"]})
    error_mm = 1e3 * np.abs(arrays["features"][:, 0].astype(np.float64) - arrays["target"].astype(np.float64))
    from matplotlib.figure import Figure

    fig = Figure(figsize=(6.4, 4.2), layout="constrained")
    ax = fig.subplots()
    upper = float(np.quantile(error_mm, 0.995))
    ax.hist(error_mm, bins=120, range=(0, upper), color="#3b6ea5")
    ax.axvline(error_mm.mean(), color="#c0392b", lw=1.5, label=f"MAE {error_mm.mean():.3f} mm")
    ax.set_xlabel(f"absolute depth error at {frequency / 1e6:g} MHz [mm]")
    ax.set_ylabel("samples (count)")
    ax.set_title(f"Raw depth error, {error_mm.size:,} samples (99.5% shown)")
    legend_below(fig)
    return save_figure(fig, png)


# --- report directories ---------------------------------------------------------------------------------

REPORT_MARKER = ".mpi-lidar-report"


@dataclass(frozen=True)
class Table:
    """A table rendered both as markdown and as HTML; cells may hold inline markdown (code, links)."""

    headers: tuple[str, ...]
    rows: tuple[tuple[str, ...], ...]

    def markdown(self) -> str:
        lines = ["| " + " | ".join(self.headers) + " |", "|" + "---|" * len(self.headers)]
        lines += ["| " + " | ".join(row) + " |" for row in self.rows]
        return "\n".join(lines)

    def html(self) -> str:
        """The table in a box of the page's width: text cells wrap, numbers stay on one line (right-aligned)."""
        head = "".join(f"<th>{_inline(h)}</th>" for h in self.headers)
        body = "".join("<tr>" + "".join(_cell_html(c) for c in row) + "</tr>" for row in self.rows)
        return f'<div class="table"><table><thead><tr>{head}</tr></thead><tbody>{body}</tbody></table></div>'


# A cell that is one number: signed, with thousands separators, a unit of %, s or x, "a / b" or "a (b)".
_NUMBER = re.compile(r"[-+]?[\d,.]+(e[-+]?\d+)?( ?(%|s|x))?( / [-+]?[\d,.]+)?( \([-+]?[\d,.]+\))?")
_LONG_WORD = 16  # characters: a cell with a longer word (a path, a scan name) may break it anywhere


def _cell_html(text: str) -> str:
    """One cell: a number right-aligned on one line, a long word breakable anywhere, other text wrapped."""
    if _NUMBER.fullmatch(text.strip()):
        return f'<td class="number">{_inline(text)}</td>'
    if any(len(word) > _LONG_WORD for word in text.split()):
        return f'<td class="long">{_inline(text)}</td>'
    return f"<td>{_inline(text)}</td>"


@dataclass(frozen=True)
class Embed:
    """Markup this package generated itself (an interactive figure), placed in the HTML report as it is.

    ``scripts`` are the files (relative to the report) it needs loaded in the page head; ``fallback`` is what
    report.md says instead.
    """

    markup: str
    fallback: str
    scripts: tuple[str, ...] = ()


Block = str | Table | Path | Embed


@lru_cache(maxsize=1)
def _markdown() -> MarkdownIt:
    # Raw HTML in text is escaped, never passed through: notes can quote file names and user strings.
    return MarkdownIt("commonmark", {"html": False})


def _inline(text: str) -> str:
    return _markdown().renderInline(text)


@lru_cache(maxsize=1)
def _template() -> jinja2.Template:
    environment = jinja2.Environment(loader=jinja2.PackageLoader("mpi_lidar.reporting", "templates"),
                                     autoescape=True, keep_trailing_newline=True)
    return environment.get_template("report.html.j2")


@dataclass
class Report:
    """A titled report of text (markdown), tables, figures and embeds: report.md, report.html, PNGs and JSON."""

    title: str
    blocks: list[Block] = field(default_factory=list)
    data: dict[str, object] = field(default_factory=dict)

    def markdown(self) -> str:
        parts = [f"# {self.title}"]
        for block in self.blocks:
            if isinstance(block, Table):
                parts.append(block.markdown())
            elif isinstance(block, Path):
                parts.append(f"![{block.stem}]({block.as_posix()})")
            elif isinstance(block, Embed):
                parts.append(block.fallback)
            else:
                parts.append(block)
        return "\n\n".join(parts) + "\n"

    def html(self) -> str:
        """The report as one HTML page (Jinja2 template; text through a markdown parser; images fit the page)."""
        rendered, scripts = [], []
        for block in self.blocks:
            if isinstance(block, Table):
                rendered.append(Markup(block.html()))
            elif isinstance(block, Path):
                rendered.append(Markup('<img src="{}" alt="{}">').format(block.as_posix(), block.stem))
            elif isinstance(block, Embed):
                rendered.append(Markup('<div class="embed">{}</div>').format(Markup(block.markup)))
                scripts += [s for s in block.scripts if s not in scripts]
            else:
                rendered.append(Markup(_markdown().render(block)))
        return _template().render(title=self.title.replace("`", ""), heading=Markup(_inline(self.title)),
                                  blocks=rendered, scripts=scripts)


def write_report(report: Report, report_dir: str | Path, figures: dict[str, Figure]) -> Path:
    """Write the report directory atomically: built beside it, then swapped in.

    A previous report of ours at the same place is replaced; any other existing directory is refused.
    """
    report_dir = Path(report_dir)
    with atomic_path(report_dir, replace=True, what="report", keep=_not_a_report) as staging:
        staging.mkdir()
        for name, fig in figures.items():
            save_figure(fig, staging / name)
        (staging / "report.md").write_text(report.markdown())
        (staging / "report.html").write_text(report.html())
        (staging / "metrics.json").write_text(
            json.dumps(report.data, indent=2, sort_keys=True, default=float) + "\n")
        (staging / REPORT_MARKER).write_text("")
    return report_dir


def write_report_to(report: Report, report_dir: str | Path, figures: dict[str, Figure]) -> str:
    """:func:`write_report` at a path, or at an object-store URL: the same folder, built in a temporary directory
    and published there, its marker last (:func:`~mpi_lidar.storage.objects.publish_report`); where it went."""
    if not is_url(report_dir):
        return str(write_report(report, report_dir, figures))
    import tempfile

    from mpi_lidar.storage.objects import publish_report

    where = location(report_dir)
    with tempfile.TemporaryDirectory(prefix="mpi-lidar-report-") as staging:
        publish_report(write_report(report, Path(staging) / "report", figures), where, REPORT_MARKER)
    return str(report_dir)


def _not_a_report(path: Path) -> bool:
    return not (path / REPORT_MARKER).exists()


def legend_below(fig: Figure) -> None:
    """The legend of a figure's axes below them, under the axis label: never over bars or points, nor over a
    title. The figure needs the constrained layout, which makes room for it."""
    handles, labels = fig.axes[0].get_legend_handles_labels()
    if handles:
        fig.legend(handles, labels, loc="outside lower center", ncols=min(len(handles), 3), frameon=False)


def error_histogram_figure(errors_mm: dict[str, np.ndarray], xlabel: str, ylabel: str = "samples (count)") -> Figure:
    """Overlaid histograms of signed errors (e.g. before and after correction), MAE in the legend below them.

    An estimate without a finite error is named in the legend as such; without any, the axes say so."""
    from matplotlib.figure import Figure

    fig = Figure(figsize=(6.4, 4.2), layout="constrained")
    ax = fig.subplots()
    finite = {label: e[np.isfinite(e)] for label, e in errors_mm.items()}
    every = np.concatenate(list(finite.values())) if finite else np.zeros(0)
    limit = max(float(np.quantile(np.abs(every), 0.995)), 1e-3) if every.size else 1.0
    for label, e in finite.items():
        if e.size:
            ax.hist(e, bins=120, range=(-limit, limit), histtype="stepfilled", alpha=0.45,
                    label=f"{label}: MAE {np.abs(e).mean():.3f} mm")
        else:
            ax.plot([], [], label=f"{label}: no finite error")
    if not every.size:
        ax.text(0.5, 0.5, "no pixel with a finite error", ha="center", va="center", transform=ax.transAxes)
    ax.set_xlabel(xlabel)
    ax.set_ylabel(ylabel)
    legend_below(fig)
    return fig


def _geometric_note(model_card: ModelCard) -> list[str]:
    """Says that a geometric model's split figures rest on synthetic geometry estimates, not on scans."""
    if not model_card.geometric:
        return []
    return ["The model takes geometric inputs (rho_ABA, d_AB). Dataset rows have no scan, so their inputs are "
            "synthetic estimates drawn from each row's true parameters with the error model of "
            "docs/results/geometry.md (section 3b): the corrected figures hold where real scans match that error."]


def evaluation_report(evaluation: Evaluation, model_card: ModelCard) -> tuple[Report, dict[str, Figure]]:
    """Report of a model on a dataset split: the metrics table and the error histogram before/after."""
    table = Table(
        ("estimate", "rows", "MAE [mm]", "RMSE [mm]", "max abs error [mm]", "bias [mm]"),
        tuple((name, f"{m.rows:,}", f"{1e3 * m.mae_m:.3f}", f"{1e3 * m.rmse_m:.3f}", f"{1e3 * m.max_abs_m:.2f}",
               f"{1e3 * m.bias_m:+.3f}") for name, m in evaluation.metrics.items()),
    )
    figure = error_histogram_figure(
        {evaluation.raw_label: 1e3 * evaluation.raw_error_m, "corrected": 1e3 * evaluation.corrected_error_m},
        "depth error [mm]",
    )
    report = Report(
        title=f"Evaluation on the {evaluation.split} split",
        blocks=[f"Dataset `{evaluation.data_path}`; model trained on dataset "
                f"{model_card.dataset.config_sha256[:12]} with the {model_card.feature_set} feature set "
                f"and the {model_card.target_mode} target.", *_geometric_note(model_card), table,
                Path("error_hist.png")],
        data={**evaluation.as_dict(), "model": {
            "feature_set": model_card.feature_set, "target_mode": model_card.target_mode,
            "geometric": model_card.geometric, "params": dict(model_card.params)}},
    )
    return report, {"error_hist.png": figure}
