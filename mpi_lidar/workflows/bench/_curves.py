"""Accuracy curves of the reference XGBoost (train rows, noise) and its error beyond the trained range."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import xgboost as xgb
from numpy.typing import NDArray

from mpi_lidar.correction import CorrectionOptions
from mpi_lidar.correction.gating import in_depth_range
from mpi_lidar.learning.features import FeatureSpec, weighted_depth
from mpi_lidar.learning.model import booster_depth
from mpi_lidar.learning.train import TrainResult, train_arrays
from mpi_lidar.workflows.bench._methods import top_depth
from mpi_lidar.workflows.bench._sample import Sample, mae


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
