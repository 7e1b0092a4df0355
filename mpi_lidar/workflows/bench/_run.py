"""The whole benchmark: every method on one train and test draw, then the curves and the out-of-range rows."""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from mpi_lidar.config import Config
from mpi_lidar.correction import CorrectionOptions
from mpi_lidar.errors import MpiLidarError
from mpi_lidar.learning.features import DEFAULT_FEATURE_SET, DEFAULT_TARGET_MODE, FeatureSpec
from mpi_lidar.learning.model import booster_depth
from mpi_lidar.workflows.bench._curves import (
    CurvePoint,
    OutOfRange,
    curve_point,
    range_guarded_depth,
    reference_xgboost,
)
from mpi_lidar.workflows.bench._measure import BenchRow, measure, score, with_pareto
from mpi_lidar.workflows.bench._methods import Predictor, gated, methods, top_depth
from mpi_lidar.workflows.bench._sample import TEST_STREAM, TRAIN_STREAM, mae, simulate

# Trees x depth; the other parameters are DEFAULT_PARAMS (learning rate 0.1).
XGB_SIZES: tuple[tuple[int, int], ...] = ((50, 4), (200, 6), (500, 8), (1000, 8))
NOISE_SCALES: tuple[float, ...] = (1.0, 0.3, 0.1, 0.01)


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
