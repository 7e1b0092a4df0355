"""Errors band by band of the true range: the raw depth, the Bayes limit and a model on the same rows.

A model meant for every range is judged per band: one MAE over 0.5-12 m would hide a model that is good near
and poor far, or the reverse, since the noise, and with it every error, grows with the range (the amplitude
falls as 1 / d^2). The default bands are octaves of range, the last one cut at 12 m, so a log-uniform d_AS
prior fills each of the first four alike.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from mpi_lidar.errors import MpiLidarError

RANGE_BANDS_M: tuple[tuple[float, float], ...] = ((0.5, 1.0), (1.0, 2.0), (2.0, 4.0), (4.0, 8.0), (8.0, 12.0))


@dataclass(frozen=True)
class BandErrors:
    """Mean absolute errors over the rows whose true d_AS lies in one band; NaN where they cannot be formed.

    band_m : (low, high) of the true d_AS; a row belongs where low <= d_AS < high (the last band of a list
        includes its high end). [m]
    rows : rows in the band. [rows]
    raw_mae_m : MAE of the raw highest-frequency depth. [m]
    limit_mae_m, limit_se_m : MAE of the posterior median (the Bayes limit) and its standard error over the
        rows. [m]
    model_mae_m, model_se_m : MAE of the model's depth and its standard error over the rows. [m]
    ratio, ratio_se : model MAE over limit MAE and its standard error by the delta method on paired rows
        (the two errors of a row are correlated, so the ratio is known better than either MAE). [1]
    """

    band_m: tuple[float, float]
    rows: int
    raw_mae_m: float
    limit_mae_m: float
    limit_se_m: float
    model_mae_m: float
    model_se_m: float
    ratio: float
    ratio_se: float


def _mae_and_se(abs_error: NDArray[np.float64]) -> tuple[float, float]:
    """Mean of absolute errors and its standard error over rows (NaN with fewer than two rows). [m]"""
    if abs_error.size == 0:
        return float("nan"), float("nan")
    se = float(abs_error.std(ddof=1) / np.sqrt(abs_error.size)) if abs_error.size > 1 else float("nan")
    return float(abs_error.mean()), se


def _ratio_and_se(model_abs: NDArray[np.float64], limit_abs: NDArray[np.float64]) -> tuple[float, float]:
    """mean(model) / mean(limit) and its delta-method standard error sd(m_i - r l_i) / (sqrt(n) mean(l)). [1]"""
    n = model_abs.size
    limit = float(limit_abs.mean()) if n else float("nan")
    if n < 2 or not limit > 0:
        return float("nan"), float("nan")
    ratio = float(model_abs.mean()) / limit
    return ratio, float((model_abs - ratio * limit_abs).std(ddof=1) / (np.sqrt(n) * limit))


def _column(values: NDArray | None, n: int, name: str) -> NDArray[np.float64]:
    if values is None:
        return np.full(n, np.nan)
    column = np.asarray(values, dtype=np.float64)
    if column.shape != (n,):
        raise MpiLidarError(f"{name} must have one value per row, shape ({n},), got {column.shape}")
    return column


def range_band_errors(true_d_as_m: NDArray, raw_depth_m: NDArray, posterior_median_m: NDArray,
                      model_depth_m: NDArray | None = None,
                      bands_m: tuple[tuple[float, float], ...] = RANGE_BANDS_M) -> list[BandErrors]:
    """Per band of true d_AS: rows, raw MAE, Bayes-limit MAE +- se, model MAE +- se, model / limit +- se.

    Parameters
    ----------
    true_d_as_m : True direct depth of each row, shape (n,). [m]
    raw_depth_m : Raw highest-frequency depth of each row, unwrapped. [m]
    posterior_median_m : Posterior median of d_AS of each row
        (:func:`mpi_lidar.learning.limits.posterior_estimates`). [m]
    model_depth_m : A model's depth of each row; None leaves the model's columns NaN. [m]
    bands_m : (low, high) bands of the true d_AS, in increasing order. [m]
    """
    truth = np.asarray(true_d_as_m, dtype=np.float64)
    if truth.ndim != 1:
        raise MpiLidarError(f"true_d_as_m must be one value per row, got shape {truth.shape}")
    n = truth.size
    raw_abs = np.abs(_column(raw_depth_m, n, "raw_depth_m") - truth)
    limit_abs = np.abs(_column(posterior_median_m, n, "posterior_median_m") - truth)
    model_abs = np.abs(_column(model_depth_m, n, "model_depth_m") - truth)
    found = []
    for index, (low, high) in enumerate(bands_m):
        last = index == len(bands_m) - 1
        inside = (truth >= low) & ((truth <= high) if last else (truth < high))
        limit_mae, limit_se = _mae_and_se(limit_abs[inside])
        model_mae, model_se = _mae_and_se(model_abs[inside])
        ratio, ratio_se = _ratio_and_se(model_abs[inside], limit_abs[inside])
        found.append(BandErrors((low, high), int(inside.sum()), _mae_and_se(raw_abs[inside])[0], limit_mae,
                                limit_se, model_mae, model_se, ratio, ratio_se))
    return found
