"""Run time against error: every depth estimator on the same simulated train and test rows.

Data are simulated in this process with the project's prior and sensor model (no store): the train rows
and the test rows come from independent seed streams, so the test set is a fresh draw from the prior and
never a near-duplicate of a training row. Each method is timed twice: its training (fit) wall time and its
inference throughput (rows per second, one process). The Pareto front marks the methods that no other
method beats on both error and time.
"""

from __future__ import annotations

import csv
import time
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass, fields
from pathlib import Path
from typing import TYPE_CHECKING, cast

import matplotlib
import numpy as np
import xgboost as xgb
from matplotlib.colors import ListedColormap
from matplotlib.figure import Figure
from numpy.typing import NDArray

from mpi_lidar.config import Config
from mpi_lidar.correction import CorrectionOptions
from mpi_lidar.correction.correct import in_depth_range
from mpi_lidar.errors import MpiLidarError
from mpi_lidar.learning.evaluate import error_metrics
from mpi_lidar.learning.features import DEFAULT_FEATURE_SET, DEFAULT_TARGET_MODE, FeatureSpec, weighted_depth
from mpi_lidar.learning.model import booster_depth
from mpi_lidar.learning.train import DEFAULT_PARAMS, TrainResult, train_arrays
from mpi_lidar.simulation.dataset import seeded_rng, simulate_rows

if TYPE_CHECKING:
    from _typeshed import DataclassInstance

    from mpi_lidar.learning.baselines import Regressor

# Seed streams of the benchmark (under the configured dataset seed): train and test never share one.
TRAIN_STREAM, TEST_STREAM = 101, 202
# Trees x depth; the other parameters are DEFAULT_PARAMS (learning rate 0.1).
XGB_SIZES: tuple[tuple[int, int], ...] = ((50, 4), (200, 6), (500, 8), (1000, 8))
NOISE_SCALES: tuple[float, ...] = (1.0, 0.3, 0.1, 0.01)


@dataclass(frozen=True)
class Sample:
    """Simulated rows: raw measurements (n, 2F) [m, V^2], the true depth d_AS (n,) [m], theta (n, 6)."""

    raw: NDArray[np.float32]
    target: NDArray[np.float64]
    theta: NDArray[np.float64]

    def __len__(self) -> int:
        return self.target.size

    def head(self, n: int) -> Sample:
        return Sample(self.raw[:n], self.target[:n], self.theta[:n])

    def inputs(self, spec: FeatureSpec) -> tuple[NDArray[np.float32], NDArray[np.float64]]:
        """The model inputs and the training target of these rows under ``spec``."""
        return spec.transform(self.raw), spec.target(self.raw, self.target)


def simulate(config: Config, n: int, stream: int, noise_scale: float | None = None,
             d_as_m: tuple[float, float] | None = None) -> Sample:
    """n rows drawn from the configured prior and measured by its sensor, from seed stream ``stream``.

    ``noise_scale`` replaces the simulator's noise scale and ``d_as_m`` the prior's d_AS range [m]
    (e.g. an out-of-range test set); everything else is the configuration's.
    """
    if noise_scale is not None:
        config = config.replace(simulator={"noise_scale": noise_scale})
    if d_as_m is not None:
        config = config.replace(prior={"d_as_m": d_as_m})
    features, theta = simulate_rows(config, n, seeded_rng(config.dataset.seed, stream))
    return Sample(features, theta[:, 0].copy(), theta)


def mae(estimate: NDArray, truth: NDArray) -> float:
    """Mean absolute error over all rows (:func:`error_metrics`); NaN if any estimate is not finite. [m]"""
    metrics = error_metrics(estimate, truth)
    return metrics.mae_m if metrics.non_finite == 0 else float("nan")


def pareto_front(error: Sequence[float], cost: Sequence[float]) -> NDArray[np.bool_]:
    """True for each point that no other point dominates (lower-or-equal error and cost, one strictly lower).

    Lower is better for both; to use a throughput, pass its negative.
    """
    e, c = np.asarray(error, dtype=np.float64), np.asarray(cost, dtype=np.float64)
    dominated = ((e[None, :] <= e[:, None]) & (c[None, :] <= c[:, None])
                 & ((e[None, :] < e[:, None]) | (c[None, :] < c[:, None])))
    return ~np.any(dominated, axis=1)


# --- estimators -------------------------------------------------------------------------------------------

Predictor = Callable[[NDArray], NDArray]


@dataclass(frozen=True)
class Method:
    """A named estimator: ``fit(train)`` returns a predictor from raw rows (n, 2F) to depth (n,) [m].

    ``gate_of`` names the method whose fitted model this one puts behind the consistency gate: the
    benchmark reuses that fit (and its training time) instead of calling ``fit`` again.
    """

    name: str
    family: str
    fit: Callable[[Sample], Predictor]
    max_test_rows: int | None = None
    gate_of: str | None = None


def _no_training(predict: Predictor) -> Callable[[Sample], Predictor]:
    return lambda _train: predict


def top_depth(frequencies_hz: tuple[float, ...]) -> Predictor:
    """The raw depth of the highest frequency (the last column of depths), as measured. [m]"""
    top = len(frequencies_hz) - 1
    return lambda raw: raw[:, top].astype(np.float64)


def _sklearn(build: Callable[[None, int], Regressor], spec: FeatureSpec, max_rows: int | None
             ) -> Callable[[Sample], Predictor]:
    def fit(train: Sample) -> Predictor:
        rows = train.head(max_rows) if max_rows else train
        model = build(None, 0)
        model.fit(spec.transform(rows.raw), spec.target(rows.raw, rows.target))
        return lambda raw: np.asarray(spec.depth(raw, model.predict(spec.transform(raw)).astype(np.float64)))
    return fit


def xgboost_method(spec: FeatureSpec, trees: int, depth: int, nthread: int = 1) -> Callable[[Sample], Predictor]:
    """XGBoost (DEFAULT_PARAMS) with a fixed number of trees of a fixed depth (no early stopping: the size is
    the point)."""
    params = {**DEFAULT_PARAMS, "max_depth": depth}

    def fit(train: Sample) -> Predictor:
        booster = train_arrays(*train.inputs(spec), params, trees, early_stopping_rounds=None, nthread=nthread).booster
        return lambda raw: booster_depth(booster, spec, raw)
    return fit


def gated(predict: Predictor, config: Config, p_value: float = 0.01) -> Predictor:
    """A predictor behind the consistency gate (mpi_lidar.correction.correct): rows it skips keep the raw depth."""
    from mpi_lidar.correction import ConsistencyGate

    gate, raw_depth = ConsistencyGate(p_value), top_depth(config.frequencies_hz)

    def predict_gated(raw: NDArray) -> NDArray:
        depth = raw_depth(raw)
        needs = gate.needs_correction(raw, config.frequencies_hz, config.sensor)
        if needs.any():
            depth[needs] = predict(raw[needs])
        return depth
    return predict_gated


def methods(config: Config, spec: FeatureSpec, xgb_sizes: Sequence[tuple[int, int]], learner_rows: int | None,
            solver_rows: int | None) -> list[Method]:
    """Every estimator of the benchmark, in table order."""
    from mpi_lidar.learning.baselines import dnn, knn, random_forest
    from mpi_lidar.physics.inverse import least_squares_two_path, prony_two_path

    freqs = config.frequencies_hz
    found = [
        Method(f"raw depth {freqs[-1] / 1e6:g} MHz", "no model", _no_training(top_depth(freqs))),
        Method("weighted depth", "no model", _no_training(lambda raw: weighted_depth(raw, freqs))),
        Method("Prony two-path", "physics", _no_training(lambda raw: prony_two_path(raw, freqs).direct_depth_m)),
        Method("least-squares two-path", "physics",
               _no_training(lambda raw: least_squares_two_path(raw, freqs).direct_depth_m), solver_rows),
        Method("KNN (k=10, distance)", "learner", _sklearn(knn, spec, learner_rows)),
        Method("RF (100 trees, depth 14)", "learner", _sklearn(random_forest, spec, learner_rows)),
        Method("MLP (64, 64)", "learner", _sklearn(dnn, spec, learner_rows)),
    ]
    for trees, depth in xgb_sizes:
        name = f"XGBoost {trees}x{depth}"
        found.append(Method(name, "xgboost", xgboost_method(spec, trees, depth)))
        found.append(Method(f"{name} + gate", "xgboost + gate", xgboost_method(spec, trees, depth), gate_of=name))
    return found


# --- measuring ----------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class BenchRow:
    """One method: errors [mm] on the test rows, fit time [s], inference throughput [rows/s], Pareto flags."""

    method: str
    family: str
    fit_rows: int
    test_rows: int
    train_s: float
    rows_per_s: float
    mae_mm: float
    rmse_mm: float
    pareto_train: bool = False
    pareto_inference: bool = False


def _throughput(predict: Predictor, raw: NDArray, min_s: float = 0.2) -> tuple[NDArray, float]:
    """Predictions of ``raw`` and rows per second, repeating fast predictors until ``min_s`` has passed."""
    started, repeats = time.perf_counter(), 0
    while True:
        estimate = predict(raw)
        repeats += 1
        elapsed = time.perf_counter() - started
        if elapsed >= min_s:
            return estimate, repeats * raw.shape[0] / elapsed


def measure(method: Method, train: Sample, test: Sample) -> tuple[BenchRow, Predictor]:
    """Fit on ``train`` (timed), predict ``test`` (timed), errors against the truth; also the predictor."""
    started = time.perf_counter()
    predict = method.fit(train)
    return score(method, predict, time.perf_counter() - started, train, test), predict


def score(method: Method, predict: Predictor, train_s: float, train: Sample, test: Sample) -> BenchRow:
    """The row of a fitted predictor: its test errors and throughput (training time as given)."""
    trained = method.family not in ("no model", "physics")
    rows = test.head(method.max_test_rows) if method.max_test_rows else test
    estimate, rows_per_s = _throughput(predict, rows.raw)
    errors = error_metrics(estimate, rows.target)
    finite = errors.non_finite == 0  # a method that fails on some rows scores NaN, not its successes alone
    return BenchRow(method.name, method.family, len(train) if trained else 0, len(rows),
                    train_s if trained else 0.0, rows_per_s,
                    1e3 * errors.mae_m if finite else float("nan"), 1e3 * errors.rmse_m if finite else float("nan"))


def with_pareto(rows: list[BenchRow]) -> list[BenchRow]:
    """The rows with their Pareto flags: error against training time, and error against throughput."""
    errors = [r.mae_mm for r in rows]
    on_train = pareto_front(errors, [r.train_s for r in rows])
    on_infer = pareto_front(errors, [-r.rows_per_s for r in rows])
    return [BenchRow(**{**asdict(r), "pareto_train": bool(a), "pareto_inference": bool(b)})
            for r, a, b in zip(rows, on_train, on_infer, strict=True)]


# --- accuracy curves and the out-of-range check ------------------------------------------------------------


def reference_xgboost(spec: FeatureSpec, train: Sample) -> TrainResult:
    """The reference XGBoost: the project's training (:func:`mpi_lidar.learning.train.train_arrays`) with its
    defaults, DEFAULT_PARAMS early-stopped on every tenth train row, in this process on one thread."""
    return train_arrays(*train.inputs(spec))


@dataclass(frozen=True)
class CurvePoint:
    """Test MAE [mm] of the reference XGBoost trained on ``train_rows`` rows at ``noise_scale``."""

    curve: str
    noise_scale: float
    train_rows: int
    trees: int
    train_s: float
    raw_mae_mm: float
    weighted_mae_mm: float
    xgboost_mae_mm: float


def curve_point(curve: str, spec: FeatureSpec, train: Sample, test: Sample, noise_scale: float,
                fitted: TrainResult | None = None) -> CurvePoint:
    fitted = fitted or reference_xgboost(spec, train)
    booster, freqs = fitted.booster, spec.frequencies_hz
    return CurvePoint(curve, noise_scale, len(train), booster.num_boosted_rounds(), fitted.wall_s,
                      1e3 * mae(top_depth(freqs)(test.raw), test.target),
                      1e3 * mae(weighted_depth(test.raw, freqs), test.target),
                      1e3 * mae(booster_depth(booster, spec, test.raw), test.target))


def range_guarded_depth(booster: xgb.Booster, spec: FeatureSpec, raw: NDArray, d_as_m: tuple[float, float],
                        tolerance_m: float = 0.0) -> NDArray[np.float64]:
    """Corrected depth [m] where the measured top-frequency depth lies in the training prior's d_AS range
    ``d_as_m`` [m] widened by ``tolerance_m`` [m], the raw depth elsewhere.

    The rule of batch correction (:func:`mpi_lidar.correction.correct.in_model_range`), on a bare booster: trees do not
    extrapolate, so a model must not touch depths it never saw. A model also learns the prior's edge (near
    the top of the range a measured depth is pulled inwards, since no true depth lies beyond it), so a
    positive tolerance lets rows from beyond the range be corrected wrongly: at +2 cm the MAE of a d_AS
    2.4-3.0 m set rises about 1.5% above the raw depth's, at 0 it stays equal (docs/results/model-range.md).
    """
    depth = top_depth(spec.frequencies_hz)(raw)
    inside = in_depth_range(depth, d_as_m, CorrectionOptions(range_tolerance_m=tolerance_m))
    if inside.any():
        depth[inside] = booster_depth(booster, spec, raw[inside])
    return depth


@dataclass(frozen=True)
class OutOfRange:
    """MAE [mm] on rows whose true d_AS lies outside the training range: raw, the model alone, range-guarded
    at no tolerance and at the batch correction's default tolerance; the share of rows the guard corrects."""

    d_as_m: tuple[float, float]
    rows: int
    raw_mae_mm: float
    model_mae_mm: float
    guarded_mae_mm: float
    guarded_correction_tolerance_mae_mm: float
    corrected_share: float


# --- the whole benchmark --------------------------------------------------------------------------------------


@dataclass(frozen=True)
class BenchPlan:
    """Sizes of one benchmark run. ``rows`` train rows, ``test_rows`` test rows, all simulated."""

    rows: int = 50_000
    test_rows: int = 25_000
    xgb_sizes: tuple[tuple[int, int], ...] = XGB_SIZES
    learner_rows: int | None = None
    solver_rows: int = 20_000
    curve_fractions: tuple[float, ...] = (1 / 64, 1 / 16, 1 / 4, 1.0)
    noise_scales: tuple[float, ...] = NOISE_SCALES
    out_of_range_d_as_m: tuple[float, float] = (2.4, 3.0)
    out_of_range_rows: int = 20_000

    @classmethod
    def quick(cls) -> BenchPlan:
        """Seconds: for tests and a first look."""
        return cls(rows=2_000, test_rows=1_000, xgb_sizes=((10, 3), (30, 4)), solver_rows=300,
                   curve_fractions=(0.25, 1.0), noise_scales=(1.0, 0.1), out_of_range_rows=1_000)

    def check(self) -> None:
        if self.rows < 100 or self.test_rows < 10:
            raise MpiLidarError(f"--rows must be at least 100 (got {self.rows}); the test set is half of it")


@dataclass(frozen=True)
class BenchResult:
    plan: BenchPlan
    feature_set: str
    target_mode: str
    rows: list[BenchRow]
    learning_curve: list[CurvePoint]
    noise_curve: list[CurvePoint]
    out_of_range: OutOfRange
    wall_s: float


def run_bench(plan: BenchPlan, config: Config | None = None, spec: FeatureSpec | None = None,
              on_step: Callable[[str], None] | None = None) -> BenchResult:
    """Every method on one train/test draw, then the learning curve, the noise curve and the out-of-range set."""
    plan.check()
    started = time.perf_counter()
    config = config or Config()
    spec = spec or FeatureSpec(config.frequencies_hz, DEFAULT_FEATURE_SET, DEFAULT_TARGET_MODE)
    step = on_step or (lambda _name: None)
    train = simulate(config, plan.rows, TRAIN_STREAM)
    test = simulate(config, plan.test_rows, TEST_STREAM)
    rows: list[BenchRow] = []
    fitted: dict[str, tuple[Predictor, float]] = {}
    for method in methods(config, spec, plan.xgb_sizes, plan.learner_rows, plan.solver_rows):
        step(method.name)
        if method.gate_of is not None:  # the gated twin of a model already trained: same model, same fit time
            predict, train_s = fitted[method.gate_of]
            rows.append(score(method, gated(predict, config), train_s, train, test))
            continue
        row, predict = measure(method, train, test)
        fitted[method.name] = predict, row.train_s
        rows.append(row)
    step("learning curve")
    learning, full = [], None
    for fraction in plan.curve_fractions:
        n = max(100, round(fraction * plan.rows))
        trained = reference_xgboost(spec, train.head(n))
        full = trained if n == plan.rows else full
        learning.append(curve_point("learning", spec, train.head(n), test, float(config.simulator.noise_scale),
                                    trained))
    step("noise curve")
    noise = []
    for scale in plan.noise_scales:
        if scale == config.simulator.noise_scale and full is not None:
            noise.append(curve_point("noise", spec, train, test, scale, full))
            continue
        noise.append(curve_point("noise", spec, simulate(config, plan.rows, TRAIN_STREAM, noise_scale=scale),
                                 simulate(config, plan.test_rows, TEST_STREAM, noise_scale=scale), scale))
    step("out of range")
    booster = (full or reference_xgboost(spec, train)).booster
    far = simulate(config, plan.out_of_range_rows, TEST_STREAM + 1, d_as_m=plan.out_of_range_d_as_m)
    guarded = range_guarded_depth(booster, spec, far.raw, config.prior.d_as_m)
    tolerant = range_guarded_depth(booster, spec, far.raw, config.prior.d_as_m,
                                   CorrectionOptions().range_tolerance_m)
    raw_far = top_depth(config.frequencies_hz)(far.raw)
    out_of_range = OutOfRange(plan.out_of_range_d_as_m, len(far), 1e3 * mae(raw_far, far.target),
                              1e3 * mae(booster_depth(booster, spec, far.raw), far.target),
                              1e3 * mae(guarded, far.target), 1e3 * mae(tolerant, far.target),
                              float(np.mean(guarded != raw_far)))
    return BenchResult(plan, spec.feature_set, spec.target_mode, with_pareto(rows), learning, noise, out_of_range,
                       time.perf_counter() - started)


# --- outputs -------------------------------------------------------------------------------------------------


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
