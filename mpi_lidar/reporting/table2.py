"""Table II of the paper, ours beside theirs: a table, a bar chart and a report."""

from __future__ import annotations

from pathlib import Path

import numpy as np
from matplotlib.figure import Figure

from mpi_lidar.learning.baselines import PAPER_RAW_MAE_MM, PAPER_TABLE2, Table2
from mpi_lidar.reporting.report import Report, Table, legend_below


def table2_table(result: Table2) -> Table:
    """Table II as a table: ours, the paper's value in brackets."""
    body = []
    for row in result.rows:
        paper = PAPER_TABLE2.get(row.name)
        ours = [f"{1e3 * v:.3f}" for v in (row.rmse_train, row.rmse_test, row.mae_train, row.mae_test)]
        theirs = [f"{v:g}" for v in paper[:4]] if paper else ["", "", "", ""]
        if row.name.startswith("raw depth"):
            theirs[3] = f"{PAPER_RAW_MAE_MM:g}"
        timing = "" if row.train_s is None else f"{row.train_s:.2f}"
        body.append((row.name, *(f"{o} ({t})" if t else o for o, t in zip(ours, theirs, strict=True)),
                     timing + (f" ({paper[4]:g})" if paper else ""), f"{row.fit_rows:,}" if row.fit_rows else ""))
    return Table(("method", "RMSE train [mm]", "RMSE test [mm]", "MAE train [mm]", "MAE test [mm]",
                  "training [s]", "fit rows"), tuple(body))


def table2_report(result: Table2) -> tuple[Report, dict[str, Figure]]:
    """Table II as a report with its bar chart."""
    report = Report(
        title="Table II: depth correction including MPI",
        blocks=["Ours (the paper's value in brackets).", table2_table(result), *result.notes, Path("table2_mae.png")],
        data={"rows": [row.__dict__ for row in result.rows], "paper": PAPER_TABLE2, "notes": result.notes},
    )
    return report, {"table2_mae.png": table2_figure(result)}


def table2_figure(result: Table2) -> Figure:
    """Test MAE of every method, ours against the paper's."""
    fig = Figure(figsize=(7, 4.4), layout="constrained")
    ax = fig.subplots()
    names = [row.name for row in result.rows]
    ax.bar(np.arange(len(names)) - 0.2, [1e3 * row.mae_test for row in result.rows], 0.4, label="ours")
    paper = [PAPER_TABLE2[n][3] if n in PAPER_TABLE2 else np.nan for n in names]
    ax.bar(np.arange(len(names)) + 0.2, paper, 0.4, label="paper")
    ax.set_xticks(np.arange(len(names)), names, rotation=30, ha="right")
    ax.set_ylabel("test MAE [mm]")
    legend_below(fig)
    return fig
