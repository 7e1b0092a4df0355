"""Accuracy of depth estimates against the truth: per-frequency raw depth, weighted depth, corrected depth."""

from __future__ import annotations

from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from mpi_lidar.learning.features import frequency_labels, weighted_depth
from mpi_lidar.learning.model import CorrectionModel
from mpi_lidar.learning.train import training_geometry
from mpi_lidar.simulation import dataset


@dataclass(frozen=True)
class ErrorMetrics:
    """Errors of an estimate against the truth, over its finite values. [m]"""

    rows: int
    mae_m: float
    rmse_m: float
    max_abs_m: float
    bias_m: float
    non_finite: int

    def as_dict(self) -> dict[str, float | int]:
        return asdict(self)


def error_metrics(estimate: NDArray, truth: NDArray) -> ErrorMetrics:
    # In place where it can be: a scan's errors are tens of millions of float64s.
    error = np.array(estimate, dtype=np.float64)
    np.subtract(error, truth, out=error)
    finite = np.isfinite(error)
    non_finite = int(error.size - np.count_nonzero(finite))
    e = error.ravel() if non_finite == 0 else error[finite]
    del error
    if e.size == 0:
        return ErrorMetrics(0, float("nan"), float("nan"), float("nan"), float("nan"), non_finite)
    bias, rmse = float(e.mean()), float(np.sqrt(np.square(e).mean()))
    np.abs(e, out=e)
    return ErrorMetrics(rows=int(e.size), mae_m=float(e.mean()), rmse_m=rmse, max_abs_m=float(e.max()), bias_m=bias,
                        non_finite=non_finite)


def raw_estimates(raw: NDArray, frequencies_hz: tuple[float, ...]) -> dict[str, NDArray[np.float64]]:
    """The estimates that need no model: each frequency's depth and the inverse-variance-weighted depth."""
    estimates = {f"raw depth {label}": raw[:, j].astype(np.float64)
                 for j, label in enumerate(frequency_labels(frequencies_hz))}
    estimates["weighted multi-frequency depth"] = weighted_depth(raw, frequencies_hz)
    return estimates


@dataclass(frozen=True)
class Evaluation:
    """Metrics of every estimate on one split, and the 31.25 MHz raw and corrected errors for plots."""

    data_path: str
    split: str
    metrics: dict[str, ErrorMetrics]
    raw_error_m: NDArray[np.float64]
    corrected_error_m: NDArray[np.float64]
    raw_label: str

    def as_dict(self) -> dict[str, object]:
        return {"data": self.data_path, "split": self.split,
                "metrics": {name: m.as_dict() for name, m in self.metrics.items()}}


def evaluate_model(model: CorrectionModel, data_path: str | Path, split: str = "test") -> Evaluation:
    """Compare raw, weighted and corrected depth on a stored split (never the rows the model trained on)."""
    sub = dataset.read_subsample(data_path, split=split)
    info = sub.info
    model.check_compatible(info.frequencies_hz, info.feature_names, f"dataset {data_path}")
    estimates = raw_estimates(sub.features, info.frequencies_hz)
    corrected = model.predict_depth(sub.features, training_geometry(model.spec, sub))
    estimates["corrected (XGBoost)"] = corrected
    raw_label = f"raw depth {frequency_labels(info.frequencies_hz)[-1]}"
    return Evaluation(
        data_path=str(data_path), split=split,
        metrics={name: error_metrics(value, sub.target) for name, value in estimates.items()},
        raw_error_m=estimates[raw_label] - sub.target, corrected_error_m=corrected - sub.target,
        raw_label=raw_label,
    )
