"""Measuring an estimator: its test error, fit time and throughput, and the Pareto fronts over them."""

from __future__ import annotations

import time
from collections.abc import Sequence
from dataclasses import asdict, dataclass

import numpy as np
from numpy.typing import NDArray

from mpi_lidar.learning.evaluate import error_metrics
from mpi_lidar.workflows.bench._methods import Method, Predictor
from mpi_lidar.workflows.bench._sample import Sample


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


def pareto_front(error: Sequence[float], cost: Sequence[float]) -> NDArray[np.bool_]:
    """True for each point that no other point dominates (lower-or-equal error and cost, one strictly lower).

    Lower is better for both; to use a throughput, pass its negative.
    """
    e, c = np.asarray(error, dtype=np.float64), np.asarray(cost, dtype=np.float64)
    dominated = ((e[None, :] <= e[:, None]) & (c[None, :] <= c[:, None])
                 & ((e[None, :] < e[:, None]) | (c[None, :] < c[:, None])))
    return ~np.any(dominated, axis=1)


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
