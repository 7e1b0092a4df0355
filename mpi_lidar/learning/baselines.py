"""The paper's Table II: KNN, random forest, SVM and a two-hidden-layer network against XGBoost.

Every learner maps the raw features (the same :class:`~mpi_lidar.learning.features.FeatureSpec` as XGBoost) to the
true depth. KNN, the forest and the network are tuned by TPE, as in the paper, on a subsample of the train
split (four fifths to fit, one fifth to validate), then refitted on the training rows with the best
parameters; that final fit is what "training time" measures. Differences from the paper, stated in the
table's notes: the SVM (RBF) learns from a subsample, because the paper's full-data SVM took 26 hours; the
network is scikit-learn's MLPRegressor with ReLU (the paper used LeakyReLU in PyTorch on a GPU); the
sklearn learners fit at most ``train_rows`` rows so that the table stays practical on two cores.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Protocol

import numpy as np
import optuna
from numpy.typing import NDArray
from sklearn.compose import TransformedTargetRegressor
from sklearn.ensemble import RandomForestRegressor
from sklearn.neighbors import KNeighborsRegressor
from sklearn.neural_network import MLPRegressor
from sklearn.pipeline import make_pipeline
from sklearn.preprocessing import StandardScaler
from sklearn.svm import SVR

from mpi_lidar.learning.evaluate import error_metrics
from mpi_lidar.learning.features import FeatureSpec, weighted_depth
from mpi_lidar.learning.model import load_model
from mpi_lidar.simulation import dataset

# Table II of the paper: RMSE train/test, MAE train/test [mm], training time [s].
PAPER_TABLE2: dict[str, tuple[float, float, float, float, float]] = {
    "KNN": (2.917, 3.645, 1.926, 2.467, 1.272),
    "RF": (6.273, 6.344, 4.675, 4.727, 54.93),
    "SVM": (7.667, 7.692, 5.597, 5.621, 95570.0),
    "DNN": (5.016, 4.577, 3.535, 3.548, 2838.0),
    "XGBoost": (2.429, 2.760, 1.759, 1.960, 267.0),
}
PAPER_RAW_MAE_MM = 9.857

Suggest = Callable[[optuna.Trial], object]
Trial = optuna.trial.BaseTrial  # a study's trial while tuning, a FixedTrial of the best parameters after


class Regressor(Protocol):
    """What the benchmarks need of a scikit-learn regressor."""

    def fit(self, x: NDArray, y: NDArray) -> object: ...

    def predict(self, x: NDArray) -> NDArray: ...


def _scaled(regressor: Regressor) -> Regressor:
    """Standardised inputs and target: distance- and gradient-based learners need comparable scales."""
    return TransformedTargetRegressor(regressor=make_pipeline(StandardScaler(), regressor),
                                      transformer=StandardScaler())


def knn(trial: Trial | None, seed: int) -> Regressor:
    k = trial.suggest_int("n_neighbors", 2, 50, log=True) if trial else 10
    weights = trial.suggest_categorical("weights", ["uniform", "distance"]) if trial else "distance"
    return _scaled(KNeighborsRegressor(n_neighbors=k, weights=weights))


def random_forest(trial: Trial | None, seed: int) -> Regressor:
    return RandomForestRegressor(
        n_estimators=trial.suggest_int("n_estimators", 50, 200, log=True) if trial else 100,
        max_depth=trial.suggest_int("max_depth", 6, 20) if trial else 14,
        min_samples_leaf=trial.suggest_int("min_samples_leaf", 1, 50, log=True) if trial else 5,
        n_jobs=2, random_state=seed,
    )


def svm(trial: Trial | None, seed: int) -> Regressor:
    return _scaled(SVR(kernel="rbf", C=10.0, epsilon=0.01, gamma="scale"))


def dnn(trial: Trial | None, seed: int) -> Regressor:
    width1 = trial.suggest_int("hidden_1", 16, 256, log=True) if trial else 64
    width2 = trial.suggest_int("hidden_2", 16, 256, log=True) if trial else 64
    return _scaled(MLPRegressor(
        hidden_layer_sizes=(width1, width2), activation="relu",
        alpha=trial.suggest_float("alpha", 1e-6, 1e-2, log=True) if trial else 1e-4,
        learning_rate_init=trial.suggest_float("learning_rate_init", 1e-4, 1e-2, log=True) if trial else 1e-3,
        early_stopping=True, max_iter=200, random_state=seed,
    ))


@dataclass(frozen=True)
class Baseline:
    name: str
    build: Callable[[Trial | None, int], Regressor]
    tuned: bool
    max_rows: int | None = None


def baselines(svm_rows: int) -> list[Baseline]:
    return [Baseline("KNN", knn, True), Baseline("RF", random_forest, True),
            Baseline("SVM", svm, False, svm_rows), Baseline("DNN", dnn, True)]


def tune_baseline(baseline: Baseline, x: NDArray, y: NDArray, trials: int, seed: int) -> dict[str, object]:
    """TPE over the baseline's space; validation MAE on a held-out fifth. Returns the best parameters."""
    holdout = np.arange(x.shape[0]) % 5 == 0

    def objective(trial: optuna.Trial) -> float:
        model = baseline.build(trial, seed)
        model.fit(x[~holdout], y[~holdout])
        return float(np.abs(model.predict(x[holdout]) - y[holdout]).mean())

    optuna.logging.set_verbosity(optuna.logging.WARNING)
    study = optuna.create_study(direction="minimize", sampler=optuna.samplers.TPESampler(seed=seed))
    study.optimize(objective, n_trials=trials)
    return dict(study.best_params)


@dataclass(frozen=True)
class Row:
    """One line of Table II, errors in metres, the training time in seconds (None where nothing is trained)."""

    name: str
    rmse_train: float
    rmse_test: float
    mae_train: float
    mae_test: float
    train_s: float | None
    fit_rows: int | None = None


@dataclass(frozen=True)
class Table2:
    rows: list[Row]
    notes: list[str]


def _row(name: str, train_estimate: NDArray, y_train: NDArray, test_estimate: NDArray, y_test: NDArray,
         train_s: float | None, fit_rows: int | None = None) -> Row:
    tr, te = error_metrics(train_estimate, y_train), error_metrics(test_estimate, y_test)
    return Row(name, tr.rmse_m, te.rmse_m, tr.mae_m, te.mae_m, train_s, fit_rows)


def table2(data_path: str | Path, model_dir: str | Path | None = None, *, train_rows: int | None = 100_000,
           trials: int = 10, tune_rows: int = 20_000, svm_rows: int = 20_000, eval_rows: int | None = 100_000,
           seed: int = 0, on_row: Callable[[Row], None] | None = None) -> Table2:
    """Every Table II row on a stored dataset's train and test splits."""
    info = dataset.dataset_info(data_path)
    spec = FeatureSpec(info.frequencies_hz)
    train = dataset.read_subsample(data_path, "train", max_rows=train_rows, seed=seed)
    train_eval = dataset.read_subsample(data_path, "train", max_rows=eval_rows, seed=seed + 1)
    test = dataset.read_subsample(data_path, "test", max_rows=eval_rows, seed=seed + 2)
    n_freq = len(info.frequencies_hz)
    rows = [
        _row(f"raw depth {info.feature_names[n_freq - 1].removeprefix('depth_')}", train_eval.features[:, n_freq - 1],
             train_eval.target, test.features[:, n_freq - 1], test.target, None),
        _row("weighted depth", weighted_depth(train_eval.features, info.frequencies_hz), train_eval.target,
             weighted_depth(test.features, info.frequencies_hz), test.target, None),
    ]
    x_train, x_eval, x_test = (spec.transform(s.features) for s in (train, train_eval, test))
    tuning = np.arange(min(tune_rows, x_train.shape[0]))
    for baseline in baselines(svm_rows):
        params = tune_baseline(baseline, x_train[tuning], train.target[tuning], trials, seed) if baseline.tuned else {}
        fit = slice(0, baseline.max_rows)
        model = baseline.build(optuna.trial.FixedTrial(params) if baseline.tuned else None, seed)
        started = time.perf_counter()
        model.fit(x_train[fit], train.target[fit])
        elapsed = time.perf_counter() - started
        rows.append(_row(baseline.name, model.predict(x_eval), train_eval.target, model.predict(x_test), test.target,
                         elapsed, x_train[fit].shape[0]))
        if on_row:
            on_row(rows[-1])
    if model_dir is not None:
        xgb_model = load_model(model_dir)
        xgb_model.check_compatible(info.frequencies_hz, info.feature_names, f"dataset {data_path}")
        training = xgb_model.card.training
        rows.append(_row("XGBoost", xgb_model.predict_depth(train_eval.features), train_eval.target,
                         xgb_model.predict_depth(test.features), test.target, training.wall_s, training.fit_rows))
    notes = [
        f"Errors on {test.rows.size:,} test rows and {train_eval.rows.size:,} train rows of {data_path}. "
        f"KNN, RF and DNN tuned by TPE ({trials} trials on {tuning.size:,} rows), then fitted on at most "
        f"{x_train.shape[0]:,} rows; the SVM (RBF, C = 10, epsilon = 0.01) fits {min(svm_rows, x_train.shape[0]):,} "
        "rows, because the paper's full-data SVM took 26 hours. DNN: scikit-learn MLP with two hidden layers and "
        "ReLU (the paper: LeakyReLU, PyTorch on a GPU). XGBoost: the model directory's own training (xgboost.dask).",
        "Why we differ: at Table I noise the multipath offset is nearly the same at the four frequencies while "
        "their noise is 1-11 mm, so no estimator can reach the paper's 1.96 mm; an independent estimate of the "
        "Bayes limit under this prior is 5.93 +- 0.18 mm (docs/results/limits.md).",
    ]
    return Table2(rows, notes)
