"""The benchmark's estimators: each a named fit from train rows to a predictor of depth."""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import NDArray

from mpi_lidar.config import Config
from mpi_lidar.learning.features import FeatureSpec, weighted_depth
from mpi_lidar.learning.model import booster_depth
from mpi_lidar.learning.train import DEFAULT_PARAMS, train_arrays
from mpi_lidar.physics.noise import NoiseModel
from mpi_lidar.workflows.bench._sample import Sample

if TYPE_CHECKING:
    from mpi_lidar.learning.baselines import Regressor

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
        needs = gate.needs_correction(raw, NoiseModel.for_sensor(config.sensor, config.frequencies_hz))
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
