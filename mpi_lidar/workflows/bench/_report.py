"""The benchmark's outputs: its tables, figures, CSV files and report."""

from __future__ import annotations

import csv
from collections.abc import Sequence
from dataclasses import asdict, fields
from pathlib import Path
from typing import TYPE_CHECKING, cast

import matplotlib
from matplotlib.colors import ListedColormap
from matplotlib.figure import Figure

from mpi_lidar.correction import CorrectionOptions
from mpi_lidar.learning.train import DEFAULT_PARAMS
from mpi_lidar.workflows.bench._curves import CurvePoint, OutOfRange
from mpi_lidar.workflows.bench._measure import BenchRow
from mpi_lidar.workflows.bench._run import BenchResult

if TYPE_CHECKING:
    from _typeshed import DataclassInstance


def _write_csv(path: Path, records: Sequence[DataclassInstance]) -> None:
    names = [f.name for f in fields(records[0])]
    with path.open("w", newline="") as handle:
        writer = csv.DictWriter(handle, fieldnames=names)
        writer.writeheader()
        for record in records:
            writer.writerow({k: (list(v) if isinstance(v, tuple) else v) for k, v in asdict(record).items()})


def _mark(flag: bool) -> str:
    return "yes" if flag else ""


def tradeoff_table(result: BenchResult):
    from mpi_lidar.reporting.report import Table

    body = tuple((r.method, r.family, f"{r.fit_rows:,}" if r.fit_rows else "", f"{r.test_rows:,}",
                  f"{r.train_s:.2f}" if r.train_s else "none", f"{r.rows_per_s:,.0f}", f"{r.mae_mm:.3f}",
                  f"{r.rmse_mm:.3f}", _mark(r.pareto_train), _mark(r.pareto_inference)) for r in result.rows)
    return Table(("method", "kind", "fit rows", "test rows", "training [s]", "inference [rows/s]",
                  "test MAE [mm]", "test RMSE [mm]", "Pareto (training)", "Pareto (inference)"), body)


def curve_table(points: list[CurvePoint]):
    from mpi_lidar.reporting.report import Table

    body = tuple((f"{p.noise_scale:g}", f"{p.train_rows:,}", str(p.trees), f"{p.train_s:.2f}", f"{p.raw_mae_mm:.3f}",
                  f"{p.weighted_mae_mm:.3f}", f"{p.xgboost_mae_mm:.3f}") for p in points)
    return Table(("noise scale", "train rows", "trees", "training [s]", "raw 31.25 MHz MAE [mm]",
                  "weighted depth MAE [mm]", "XGBoost MAE [mm]"), body)


def out_of_range_table(o: OutOfRange):
    from mpi_lidar.reporting.report import Table

    tol = CorrectionOptions().range_tolerance_m
    return Table(("true d_AS [m]", "rows", "raw MAE [mm]", "model alone MAE [mm]", "range-guarded MAE [mm]",
                  f"guarded, +{100 * tol:g} cm tolerance [mm]", "rows corrected (guarded)"),
                 ((f"{o.d_as_m[0]:g}-{o.d_as_m[1]:g}", f"{o.rows:,}", f"{o.raw_mae_mm:.3f}", f"{o.model_mae_mm:.3f}",
                   f"{o.guarded_mae_mm:.3f}", f"{o.guarded_correction_tolerance_mae_mm:.3f}",
                   f"{100 * o.corrected_share:.1f}%"),))


def tradeoff_figure(rows: list[BenchRow]) -> Figure:
    """Test MAE against training time and against inference throughput, Pareto fronts drawn as steps."""
    fig = Figure(figsize=(13, 5.5))
    axes = fig.subplots(1, 2)
    trained = [r.train_s for r in rows if r.train_s > 0]
    floor = 0.3 * min(trained) if trained else 1e-3
    panels = ((axes[0], [max(r.train_s, floor) for r in rows], "pareto_train",
               f"training time [s] (no training drawn at {floor:.2g} s)"),
              (axes[1], [r.rows_per_s for r in rows], "pareto_inference", "inference throughput [rows/s]"))
    families = sorted({r.family for r in rows})
    tab10 = cast(ListedColormap, matplotlib.colormaps["tab10"])  # a listed map: its colours are RGB triples
    colors = dict(zip(families, cast("Sequence[tuple[float, float, float]]", tab10.colors), strict=False))
    for ax, x, flag, label in panels:
        for r, xi in zip(rows, x, strict=True):
            on = getattr(r, flag)
            ax.scatter(xi, r.mae_mm, color=colors[r.family], s=60 if on else 25,
                       edgecolors="black" if on else "none", zorder=3)
            ax.annotate(r.method, (xi, r.mae_mm), fontsize=7, xytext=(3, 3), textcoords="offset points")
        front = sorted((xi, r.mae_mm) for r, xi in zip(rows, x, strict=True) if getattr(r, flag))
        if front:
            ax.step(*zip(*front, strict=True), where="post" if flag == "pareto_train" else "pre",
                    color="black", lw=0.8, ls="--", label="Pareto front")
        ax.set_xscale("log")
        ax.set_xlabel(label)
        ax.set_ylabel("test MAE [mm]")
        ax.grid(alpha=0.3)
    for family in families:
        axes[0].scatter([], [], color=colors[family], label=family)
    axes[0].legend(fontsize=8)
    fig.tight_layout()
    return fig


def curve_figure(points: list[CurvePoint], x_name: str, xlabel: str) -> Figure:
    fig = Figure(figsize=(6, 4))
    ax = fig.subplots()
    x = [getattr(p, x_name) for p in points]
    for name, label in (("raw_mae_mm", "raw 31.25 MHz"), ("weighted_mae_mm", "weighted depth"),
                        ("xgboost_mae_mm", "XGBoost")):
        ax.plot(x, [getattr(p, name) for p in points], "o-", label=label)
    ax.set_xscale("log")
    ax.set_xlabel(xlabel)
    ax.set_ylabel("test MAE [mm]")
    ax.grid(alpha=0.3)
    ax.legend()
    fig.tight_layout()
    return fig


def write_bench(result: BenchResult, out_dir: str | Path, machine: str = "") -> Path:
    """report.md/.html, metrics.json, tradeoff.png, learning_curve.png, noise.png and one CSV per table."""
    from mpi_lidar.reporting.report import Report, write_report

    p = result.plan
    notes = (f"Train rows: {p.rows:,}, test rows: {p.test_rows:,}, independent draws from the default prior "
             f"(separate seed streams). Learners and XGBoost use the '{result.feature_set}' feature set and the "
             f"'{result.target_mode}' target. Training time is the fit's wall time in this process; throughput is "
             "one process predicting the test rows (the gate's own cost included). XGBoost sizes are trees x depth "
             f"at learning rate {DEFAULT_PARAMS['learning_rate']:g}, no early stopping, one thread; '+ gate' corrects "
             "only the rows the consistency gate flags and keeps the raw depth elsewhere. The least-squares solver "
             f"is timed and scored on the first {p.solver_rows:,} test rows. A point is on a Pareto front when no "
             "other method has both a lower-or-equal MAE and a lower-or-equal time (one of them strictly lower). "
             f"{machine}Total wall time {result.wall_s:.0f} s.")
    report = Report(
        title="Run time against error",
        blocks=[notes, tradeoff_table(result), Path("tradeoff.png"),
                "Learning curve: the reference XGBoost (the project's default parameters, early-stopped on every "
                "tenth train row) on the first n train rows, scored on the same test rows.",
                curve_table(result.learning_curve), Path("learning_curve.png"),
                "Noise curve: train and test rows simulated at each noise scale (1 = Table I).",
                curve_table(result.noise_curve), Path("noise.png"),
                "Out-of-range rows (true d_AS beyond the training prior): the model alone against the range-guarded "
                "correction (raw depth where the measured depth lies outside the trained range, as in batch "
                "correction), with no tolerance and with batch correction's default tolerance.",
                out_of_range_table(result.out_of_range)],
        data={"plan": asdict(p), "rows": [asdict(r) for r in result.rows],
              "learning_curve": [asdict(c) for c in result.learning_curve],
              "noise_curve": [asdict(c) for c in result.noise_curve],
              "out_of_range": asdict(result.out_of_range), "wall_s": result.wall_s},
    )
    figures = {"tradeoff.png": tradeoff_figure(result.rows),
               "learning_curve.png": curve_figure(result.learning_curve, "train_rows", "train rows"),
               "noise.png": curve_figure(result.noise_curve, "noise_scale", "noise scale (1 = Table I)")}
    out = write_report(report, out_dir, figures)
    _write_csv(out / "tradeoff.csv", result.rows)
    _write_csv(out / "learning_curve.csv", result.learning_curve)
    _write_csv(out / "noise.csv", result.noise_curve)
    _write_csv(out / "out_of_range.csv", [result.out_of_range])
    return out
