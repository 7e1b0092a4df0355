"""Report pieces written as files: markdown tables and PNG figures (written atomically)."""

from __future__ import annotations

import os
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np

from mpi_lidar import dataset


def generation_markdown(summary: dataset.DatasetSummary, run: dataset.GenerationReport, workers: str) -> str:
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


def save_figure(fig: plt.Figure, path: str | Path) -> Path:
    """Save a figure through a temporary file and a rename, so a reader never sees half a PNG."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    staging = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    try:
        fig.savefig(staging, dpi=120, bbox_inches="tight", format="png")
        os.replace(staging, path)
    finally:
        plt.close(fig)
        staging.unlink(missing_ok=True)
    return path


def depth_error_histogram(store: str | Path, png: str | Path, frequency_index: int = -1) -> Path:
    """Histogram of the absolute raw depth error at one frequency (the paper's Fig. 5: 31.25 MHz)."""
    group = dataset.open_store(store)
    frequency = group.attrs["frequencies_hz"][frequency_index]
    column = frequency_index % len(group.attrs["frequencies_hz"])
    error_mm = 1e3 * np.abs(group["features"][:, column].astype(np.float64) - group["target"][:])
    fig, ax = plt.subplots(figsize=(6.4, 4.0))
    upper = float(np.quantile(error_mm, 0.995))
    ax.hist(error_mm, bins=120, range=(0, upper), color="#3b6ea5")
    ax.axvline(error_mm.mean(), color="#c0392b", lw=1.5, label=f"MAE {error_mm.mean():.3f} mm")
    ax.set_xlabel(f"absolute depth error at {frequency / 1e6:g} MHz [mm]")
    ax.set_ylabel("samples")
    ax.set_title(f"Raw depth error, {error_mm.size:,} samples (99.5% shown)")
    ax.legend()
    return save_figure(fig, png)
