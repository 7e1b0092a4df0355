"""Training XGBoost through its Dask interface on the stored train split, read lazily from Zarr.

Early stopping watches a validation set carved from the train split (every tenth train row; rows are
independent draws, so any fixed subset is an unbiased sample). The test split is never seen here.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path

import dask.array as da
import numpy as np
import xgboost as xgb
import xgboost.dask as dxgb
from distributed import Client
from numpy.typing import NDArray

from mpi_lidar.errors import MpiLidarError
from mpi_lidar.learning.features import GEOMETRY_ERROR_MODEL, FeatureSpec, synthetic_geometry, synthetic_geometry_dask
from mpi_lidar.learning.model import save_model
from mpi_lidar.simulation import dataset

VALIDATION_EVERY = 10
# Absolute error: the model then estimates the posterior median of the depth, which minimises the MAE (the
# multipath bias is one-sided, so the mean is off): 5.87 mm against 6.01 mm for squared error (docs/tradeoff.md).
BASE_PARAMS: dict[str, object] = {"objective": "reg:absoluteerror", "tree_method": "hist", "eval_metric": "mae"}
DEFAULT_PARAMS: dict[str, object] = {
    "max_depth": 8, "learning_rate": 0.1, "subsample": 0.8, "colsample_bytree": 1.0,
    "min_child_weight": 1.0, "reg_lambda": 1.0, "gamma": 0.0,
}
DEFAULT_ROUNDS = 2000
DEFAULT_EARLY_STOPPING = 50


@dataclass(frozen=True)
class TrainResult:
    booster: xgb.Booster
    best_iteration: int
    validation_mae_m: float
    fit_rows: int
    validation_rows: int
    wall_s: float


def train_split_masks(split: da.Array) -> tuple[da.Array, da.Array]:
    """(fit, validation) boolean masks over all rows: train rows, every tenth one held for validation."""
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
    """Train on the full train split of a complete dataset with xgboost.dask, early-stopped on validation."""
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
    dtrain = dxgb.DaskQuantileDMatrix(client, x_fit, y_fit)
    dval = dxgb.DaskQuantileDMatrix(client, x_val, y_val, ref=dtrain)
    output = dxgb.train(
        client, {**BASE_PARAMS, **(params or DEFAULT_PARAMS)}, dtrain, num_boost_round=num_boost_round,
        evals=[(dval, "validation")], early_stopping_rounds=early_stopping_rounds, verbose_eval=False,
    )
    booster: xgb.Booster = output["booster"]
    history = output["history"]["validation"]["mae"]
    best = booster.best_iteration if booster.best_iteration is not None else len(history) - 1
    return TrainResult(booster, int(best), float(history[best]), fit_rows, val_rows, time.perf_counter() - started)


def training_geometry_lazy(spec: FeatureSpec, lazy: dataset.LazyDataset) -> da.Array | None:
    """Synthetic geometric inputs for every stored row (lazy), or None for a model without them."""
    if not spec.geometric:
        return None
    info = lazy.info
    return synthetic_geometry_dask(lazy.theta, info.theta_names, info.config.prior, info.config.dataset.seed)


def training_geometry(spec: FeatureSpec, sub: dataset.Subsample) -> NDArray | None:
    """Synthetic geometric inputs for the rows of a subsample (same values as for the same rows in training)."""
    if not spec.geometric:
        return None
    info = sub.info
    return synthetic_geometry(sub.theta, info.theta_names, info.config.prior, info.config.dataset.seed, sub.rows)


def _rows(array: da.Array, mask: da.Array) -> da.Array:
    selected = array[mask]
    selected.compute_chunk_sizes()
    return selected


def check_dataset_matches(spec: FeatureSpec, info: dataset.DatasetInfo) -> None:
    if tuple(spec.frequencies_hz) != tuple(info.frequencies_hz) or spec.raw_names != list(info.feature_names):
        raise MpiLidarError(f"dataset {info.path} has columns {list(info.feature_names)}, the features expect "
                            f"{spec.raw_names}; use a dataset simulated at the model's frequencies")


def model_card(spec: FeatureSpec, info: dataset.DatasetInfo, params: dict[str, object],
               result: TrainResult, workers: int) -> dict[str, object]:
    """Everything a correction run needs to know about the model, and how it was made."""
    return {
        "frequencies_hz": list(spec.frequencies_hz),
        "raw_feature_names": spec.raw_names,
        "feature_set": spec.feature_set,
        "feature_names": spec.names,
        "geometric": spec.geometric,
        **({"geometry_error_model": dict(GEOMETRY_ERROR_MODEL)} if spec.geometric else {}),
        "target_mode": spec.target_mode,
        "residual_reference": spec.residual_reference,
        "dataset": {"path": info.path, "config_sha256": info.config_sha256, "samples": info.samples,
                    "prior": info.config.prior.model_dump(mode="json"),
                    "simulator": info.config.simulator.model_dump(mode="json")},
        "params": {**BASE_PARAMS, **params},
        "num_boost_round": result.best_iteration + 1,
        "metrics": {"validation_mae_m": result.validation_mae_m},
        "training": {"fit_rows": result.fit_rows, "validation_rows": result.validation_rows,
                     "wall_s": round(result.wall_s, 3), "dask_workers": workers},
    }


def train_and_save(
    client: Client, data_path: str | Path, out_dir: str | Path, spec: FeatureSpec,
    params: dict[str, object] | None = None, **train_options: int,
) -> tuple[Path, TrainResult]:
    """Train on the cluster and write the model directory (the booster trimmed to its best iteration)."""
    out_dir = Path(out_dir)
    if out_dir.exists():
        raise MpiLidarError(f"model directory {out_dir} already exists; choose another --out or remove it")
    params = dict(params or DEFAULT_PARAMS)
    result = train_dask(client, data_path, spec, params, **train_options)
    best = result.booster[: result.best_iteration + 1]
    info = dataset.dataset_info(data_path)
    card = model_card(spec, info, params, result, len(client.scheduler_info()["workers"]))
    return save_model(out_dir, best, card), result
