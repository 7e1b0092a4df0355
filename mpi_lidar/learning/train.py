"""Training XGBoost: through its Dask interface on the stored train split, read lazily from Zarr
(:func:`train_dask`), or in this process on arrays in memory (:func:`train_arrays`, for benchmarks).

Both take their parameters from :func:`xgb_params` and early-stop on a validation set of every tenth row
(of the train split; rows are independent draws, so any fixed subset is an unbiased sample), and both
return the booster trimmed to its best iteration. The test split is never seen here. :func:`train_dask` fits the
corrected depths' uncertainty on the same validation rows (:mod:`mpi_lidar.learning.error_model`).
"""

from __future__ import annotations

import ctypes
import logging
import time
import warnings
from collections.abc import Mapping
from dataclasses import dataclass, replace
from pathlib import Path
from typing import TYPE_CHECKING, overload

import numpy as np
from numpy.typing import NDArray

from mpi_lidar.config import SensorConfig
from mpi_lidar.errors import MpiLidarError
from mpi_lidar.learning.error_model import error_terms, fit_uncertainty
from mpi_lidar.learning.features import GEOMETRY_ERROR_MODEL, FeatureSpec, synthetic_geometry, synthetic_geometry_dask
from mpi_lidar.learning.model import ModelCard, booster_sha256, package_versions, save_model, staged_model
from mpi_lidar.learning.model_card import (
    MODEL_SCHEMA,
    DatasetCard,
    GeometryErrorCard,
    MetricsCard,
    TrainingCard,
    UncertaintyCard,
)
from mpi_lidar.locations import location
from mpi_lidar.simulation import dataset

if TYPE_CHECKING:
    import dask.array as da
    import xgboost as xgb  # imported where a model is trained: importing XGBoost imports scikit-learn (~1 s)
    from distributed import Client

VALIDATION_EVERY = 10
# Absolute error: the model then estimates the posterior median of the depth, which minimises the MAE (the
# multipath bias is one-sided, so the mean is off): 5.87 mm against 6.01 mm for squared error
# (docs/results/tradeoff.md).
BASE_PARAMS: dict[str, object] = {"objective": "reg:absoluteerror", "tree_method": "hist", "eval_metric": "mae"}
DEFAULT_PARAMS: dict[str, object] = {
    "max_depth": 8, "learning_rate": 0.1, "subsample": 0.8, "colsample_bytree": 1.0,
    "min_child_weight": 1.0, "reg_lambda": 1.0, "gamma": 0.0,
}
# What a parameter file may set, and the values XGBoost accepts for each (checked before any work starts).
PARAM_BOUNDS: dict[str, tuple[type, float, float]] = {
    "max_depth": (int, 0, 64), "learning_rate": (float, 1e-6, 1.0), "subsample": (float, 1e-6, 1.0),
    "colsample_bytree": (float, 1e-6, 1.0), "min_child_weight": (float, 0.0, 1e6), "reg_lambda": (float, 0.0, 1e6),
    "gamma": (float, 0.0, 1e6),
}
DEFAULT_ROUNDS = 2000


def check_params(params: Mapping[str, object], source: str) -> dict[str, object]:
    """Parameters within :data:`PARAM_BOUNDS`; one :class:`MpiLidarError` naming ``source`` otherwise."""
    unknown = sorted(set(params) - set(PARAM_BOUNDS))
    if unknown:
        raise MpiLidarError(f"{source}: unknown parameters {unknown}; known: {sorted(PARAM_BOUNDS)}")
    for name, value in params.items():
        kind, low, high = PARAM_BOUNDS[name]
        if (not isinstance(value, int | float) or isinstance(value, bool)
                or (kind is int and value != int(value)) or not low <= value <= high):
            raise MpiLidarError(f"{source}: {name} = {value!r} must be {'an integer' if kind is int else 'a number'} "
                                f"in [{low:g}, {high:g}]")
    return dict(params)
DEFAULT_EARLY_STOPPING = 50


def xgb_params(params: Mapping[str, object] | None = None, **overrides: object) -> dict[str, object]:
    """The parameters XGBoost trains with: BASE_PARAMS (objective, tree method, metric), then ``params``
    (DEFAULT_PARAMS when None), then ``overrides`` (e.g. ``nthread``). The card records this dict."""
    return {**BASE_PARAMS, **(DEFAULT_PARAMS if params is None else params), **overrides}


@dataclass(frozen=True)
class TrainResult:
    """A trained booster, trimmed to its best iteration, and how it was trained.

    Without a validation set (no early stopping) ``validation_rows`` is 0 and ``validation_mae_m`` NaN.
    ``uncertainty`` is the corrected depths' uncertainty fitted on the validation rows (None where it was not:
    :func:`train_arrays` has no raw rows to fit it on).
    """

    booster: xgb.Booster
    best_iteration: int
    validation_mae_m: float
    fit_rows: int
    validation_rows: int
    wall_s: float
    uncertainty: UncertaintyCard | None = None


def _early_stopped(booster: xgb.Booster, history: dict[str, list[float]], fit_rows: int, validation_rows: int,
                   started: float) -> TrainResult:
    """The result of a run early-stopped on a validation set: the booster trimmed to its best iteration,
    and the validation metric (the last, which early stopping watches) there."""
    scores = history[next(reversed(history))]
    best = booster.best_iteration if booster.best_iteration is not None else len(scores) - 1
    return TrainResult(booster[: best + 1], int(best), float(scores[best]), fit_rows, validation_rows,
                       time.perf_counter() - started)


def train_arrays(
    x: NDArray,
    y: NDArray,
    params: Mapping[str, object] | None = None,
    num_boost_round: int = DEFAULT_ROUNDS,
    early_stopping_rounds: int | None = DEFAULT_EARLY_STOPPING,
    nthread: int = 1,
) -> TrainResult:
    """Train XGBoost in this process on model inputs ``x`` (n, k) and targets ``y`` (n,).

    ``params`` as for :func:`xgb_params` (with ``nthread`` and seed 0). With ``early_stopping_rounds``, every
    tenth row is held out to stop on and the booster is trimmed to its best iteration; with None, all rows
    are fitted for ``num_boost_round`` rounds. ``wall_s`` is the fit's wall time, data preparation included.
    """
    import xgboost as xgb

    full = xgb_params(params, nthread=nthread, seed=0)
    started = time.perf_counter()
    if not early_stopping_rounds:
        booster = xgb.train(full, xgb.QuantileDMatrix(x, y, nthread=nthread), num_boost_round, verbose_eval=False)
        return TrainResult(booster, num_boost_round - 1, float("nan"), int(y.size), 0, time.perf_counter() - started)
    hold = np.arange(y.size) % VALIDATION_EVERY == 0
    dfit = xgb.QuantileDMatrix(x[~hold], y[~hold], nthread=nthread)
    dval = xgb.QuantileDMatrix(x[hold], y[hold], ref=dfit, nthread=nthread)
    history: dict[str, dict[str, list[float]]] = {}
    booster = xgb.train(full, dfit, num_boost_round, evals=[(dval, "validation")], evals_result=history,
                        early_stopping_rounds=early_stopping_rounds, verbose_eval=False)
    return _early_stopped(booster, history["validation"], int((~hold).sum()), int(hold.sum()), started)


def train_split_masks(split: da.Array) -> tuple[da.Array, da.Array]:
    """(fit, validation) boolean masks over all rows: train rows, every tenth one held for validation."""
    import dask.array as da

    row = da.arange(split.shape[0], chunks=split.chunks)
    is_train = split == dataset.SPLIT_CODES["train"]
    holdout = row % VALIDATION_EVERY == 0
    return is_train & ~holdout, is_train & holdout


def train_dask(
    client: Client,
    data_path: str | Path,
    spec: FeatureSpec,
    params: dict[str, object] | None = None,
    num_boost_round: int = DEFAULT_ROUNDS,
    early_stopping_rounds: int = DEFAULT_EARLY_STOPPING,
) -> TrainResult:
    """Train on the full train split of a complete dataset with xgboost.dask, early-stopped on validation, and fit
    the corrected depths' uncertainty on the validation rows (:func:`validation_error_terms`)."""
    import xgboost.dask as dxgb  # its imports (pandas, distributed) cost seconds that correction never needs

    lazy = dataset.read_lazy(data_path)
    check_dataset_matches(spec, lazy.info)
    fit, validation = train_split_masks(lazy.split)
    x = spec.transform(lazy.features, training_geometry_lazy(spec, lazy))
    y = spec.target(lazy.features, lazy.target)
    x_fit, y_fit = _rows(x, fit), _rows(y, fit)
    x_val, y_val = _rows(x, validation), _rows(y, validation)
    fit_rows, val_rows = int(np.nansum(x_fit.chunks[0])), int(np.nansum(x_val.chunks[0]))
    if fit_rows == 0 or val_rows == 0:
        raise MpiLidarError(f"dataset {data_path} has no train rows to fit on; regenerate it with more samples")
    started = time.perf_counter()
    quiet_native_log(client)
    dtrain = dxgb.DaskQuantileDMatrix(client, x_fit, y_fit)
    dval = dxgb.DaskQuantileDMatrix(client, x_val, y_val, ref=dtrain)
    output = dxgb.train(
        client, xgb_params(params or None), dtrain, num_boost_round=num_boost_round,
        evals=[(dval, "validation")], early_stopping_rounds=early_stopping_rounds, verbose_eval=False,
    )
    result = _early_stopped(output["booster"], output["history"]["validation"], fit_rows, val_rows, started)
    terms = validation_error_terms(client, result.booster, spec, lazy, validation, x_val)
    return replace(result, uncertainty=fit_uncertainty(terms))


def validation_error_terms(client: Client, booster: xgb.Booster, spec: FeatureSpec, lazy: dataset.LazyDataset,
                           validation: da.Array, x_val: da.Array) -> NDArray[np.float64]:
    """:func:`~mpi_lidar.learning.error_model.error_terms` of the validation rows (``validation`` mask over the
    stored rows, ``x_val`` their model inputs), predicted on the cluster: only the three columns come back, and for
    a geometric model the two geometric inputs it read (rho_ABA, d_AB), for the fit's regions of the prior."""
    import dask.array as da
    import xgboost.dask as dxgb

    config = lazy.info.config
    raw, true_depth = _rows(lazy.features, validation), _rows(lazy.target, validation)
    depth = spec.depth(raw, dxgb.inplace_predict(client, booster, x_val).astype(np.float64))
    # Columns of one block each, so that the blocks pair up by rows.
    terms = da.map_blocks(_error_terms_block, raw, depth[:, None], true_depth[:, None], dtype=np.float64,
                          chunks=(raw.chunks[0], (3,)), frequencies_hz=tuple(spec.frequencies_hz),
                          sensor=config.sensor, noise_scale=config.simulator.noise_scale)
    if spec.geometric:
        geometric = x_val[:, -2:].astype(np.float64).rechunk((raw.chunks[0], -1))
        terms = da.concatenate([terms, geometric], axis=1)
    return np.asarray(client.compute(terms).result())


def _error_terms_block(raw: NDArray, depth: NDArray, true_depth: NDArray, frequencies_hz: tuple[float, ...],
                       sensor: SensorConfig, noise_scale: float) -> NDArray[np.float64]:
    return error_terms(raw, depth[:, 0], true_depth[:, 0], frequencies_hz, sensor, noise_scale)


_native_log: object | None = None  # the ctypes function, kept alive here: the library calls it for as long as it runs


def _log_native(message: bytes) -> None:
    text = message.decode(errors="replace").strip()
    if "WARNING" in text:
        warnings.warn(text, UserWarning, stacklevel=2)
    else:
        logging.getLogger("xgboost").info(text)


def route_native_log() -> None:
    """Send the XGBoost library's log lines of this thread to Python: warnings as warnings, the rest to the
    ``xgboost`` logger (INFO) instead of stderr.

    The library writes its console lines (such as each Dask worker's "Task ... got rank N" when training joins
    the workers) straight to stderr from every thread that has not registered a log function; ``import
    xgboost`` registers one only in the thread that imports it.
    """
    from xgboost.core import _LIB

    global _native_log
    if _native_log is None:
        _native_log = ctypes.CFUNCTYPE(None, ctypes.c_char_p)(_log_native)
    _LIB.XGBRegisterLogCallback(_native_log)


def quiet_native_log(client: Client) -> None:
    """:func:`route_native_log` in the task thread of every worker of ``client`` (a worker of the command line's
    clusters has one), before training there."""
    workers = list(client.scheduler_info()["workers"])
    client.gather([client.submit(route_native_log, workers=[w], allow_other_workers=False, pure=False)
                   for w in workers])


def training_geometry_lazy(spec: FeatureSpec, lazy: dataset.LazyDataset) -> da.Array | None:
    """Synthetic geometric inputs for every stored row (lazy), or None for a model without them."""
    if not spec.geometric:
        return None
    info = lazy.info
    return synthetic_geometry_dask(lazy.theta, info.theta_names, info.config.dataset.seed)


def training_geometry(spec: FeatureSpec, sub: dataset.Subsample) -> NDArray | None:
    """Synthetic geometric inputs for the rows of a subsample (same values as for the same rows in training)."""
    if not spec.geometric:
        return None
    info = sub.info
    return synthetic_geometry(sub.theta, info.theta_names, info.config.dataset.seed, sub.rows)


def _rows(array: da.Array, mask: da.Array) -> da.Array:
    selected = array[mask]
    selected.compute_chunk_sizes()
    return selected


def check_dataset_matches(spec: FeatureSpec, info: dataset.DatasetInfo) -> None:
    if tuple(spec.frequencies_hz) != tuple(info.frequencies_hz) or spec.raw_names != list(info.feature_names):
        raise MpiLidarError(f"dataset {info.path} has columns {list(info.feature_names)}, the features expect "
                            f"{spec.raw_names}; use a dataset simulated at the model's frequencies")


def model_card(spec: FeatureSpec, dataset_card: DatasetCard, params: Mapping[str, object] | None,
               result: TrainResult, workers: int) -> ModelCard:
    """Everything a correction run needs to know about the model, and how it was made.

    ``params`` as given to the training (see :func:`xgb_params`); ``workers`` the Dask workers (0 in process).
    The model hash and package versions are those of ``result.booster`` here; :func:`save_model` records the
    written file's.
    """
    return ModelCard(
        schema=MODEL_SCHEMA,
        frequencies_hz=spec.frequencies_hz,
        raw_feature_names=spec.raw_names,
        feature_set=spec.feature_set,
        feature_names=spec.names,
        geometric=spec.geometric,
        geometry_error_model=GeometryErrorCard(**GEOMETRY_ERROR_MODEL) if spec.geometric else None,
        uncertainty_model=result.uncertainty,
        target_mode=spec.target_mode,
        residual_reference=spec.residual_reference,
        dataset=dataset_card,
        params=xgb_params(params),
        num_boost_round=result.best_iteration + 1,
        metrics=MetricsCard(validation_mae_m=result.validation_mae_m),
        training=TrainingCard(fit_rows=result.fit_rows, validation_rows=result.validation_rows,
                              wall_s=round(result.wall_s, 3), dask_workers=workers),
        versions=package_versions(),
        model_sha256=booster_sha256(result.booster),
    )


def dataset_card(info: dataset.DatasetInfo) -> DatasetCard:
    """The card's description of a stored dataset."""
    return DatasetCard.from_config(info.config, path=info.path, sha256=info.config_sha256, samples=info.samples)


@overload
def train_and_save(client: Client, data_path: str | Path, out_dir: Path, spec: FeatureSpec,
                   params: dict[str, object] | None = None, **train_options: int) -> tuple[Path, TrainResult]: ...


@overload
def train_and_save(client: Client, data_path: str | Path, out_dir: str | Path, spec: FeatureSpec,
                   params: dict[str, object] | None = None, **train_options: int) -> tuple[str | Path, TrainResult]: ...


def train_and_save(
    client: Client, data_path: str | Path, out_dir: str | Path, spec: FeatureSpec,
    params: dict[str, object] | None = None, **train_options: int,
) -> tuple[str | Path, TrainResult]:
    """Train on the cluster and write the model directory (the booster trimmed to its best iteration): a path,
    or an object-store URL, where a model already there is refused before the training and the new one is
    published whole once trained (:func:`~mpi_lidar.learning.model.staged_model`). Gives back ``out_dir``
    (a URL as its text) and the training's result."""
    with staged_model(out_dir) as target:
        if target.exists():
            raise MpiLidarError(f"model directory {out_dir} already exists; choose another --out or remove it")
        params = dict(params or DEFAULT_PARAMS)
        result = train_dask(client, data_path, spec, params, **train_options)
        card = model_card(spec, dataset_card(dataset.dataset_info(data_path)), params, result,
                          len(client.scheduler_info()["workers"]))
        written = save_model(target, result.booster, card)
    where = location(out_dir)
    return (written if where.is_local else where.url), result
