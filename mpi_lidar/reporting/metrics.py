"""Errors of a corrected scan against its reference depth, per region, and what correction did per pixel."""

from __future__ import annotations

import numpy as np

from mpi_lidar.correction import INVALID_FLAGS, MODEL_FLAGS, Correction
from mpi_lidar.reporting.report import Table
from mpi_lidar.scans.scan import Scan

# Pixels per band of rows that :func:`scan_metrics` works on at once.
METRIC_BAND_PIXELS = 1 << 20


def measured_depth(scan: Scan, correction: Correction, rows: slice = slice(None)) -> np.ndarray:
    """The highest frequency's measured depth of a range of rows (h, W) [m]: unwrapped into one range where
    correction unwrapped it (:attr:`Correction.measured_depth`), the scan's own otherwise."""
    if correction.measured_depth is not None:
        return correction.measured_depth[rows]
    return np.asarray(scan.depth[-1, rows])


def amplitude_v2(scan: Scan, correction: Correction) -> np.ndarray:
    """The highest frequency's amplitude (H, W) in V^2: the scan's, divided by the scanner's unit per V^2 that
    correction read them in (:attr:`Correction.amplitude_units_per_v2`)."""
    return np.asarray(scan.amplitude[-1], dtype=np.float32) / np.float32(correction.amplitude_units_per_v2)


def metric_regions(scan: Scan, correction: Correction, rows: slice = slice(None)) -> dict[str, np.ndarray]:
    """Where the metrics are taken, per region, for a range of rows: pixels with a reference depth and a
    valid measurement (whole map), and those of them in the reference mask (masked region)."""
    if scan.reference_depth is None:
        return {}
    usable = np.isfinite(scan.reference_depth[rows]) & ~np.isin(correction.flags[rows],
                                                                [int(f) for f in INVALID_FLAGS])
    regions = {"whole map": usable}
    if scan.reference_mask is not None:
        regions["masked region"] = usable & scan.reference_mask[rows]
    return regions


def scan_metrics(scan: Scan, correction: Correction) -> dict[str, dict[str, float]]:
    """MAE, RMSE and max error of the raw highest-frequency depth (:func:`measured_depth`) and of the corrected
    depth, per region. [m]

    Summed a band of rows at a time (:data:`METRIC_BAND_PIXELS`), so a scan kept in its store is read one
    band at a time and the float64 errors of the whole scan never exist at once.
    """
    if scan.reference_depth is None:
        return {}
    h, w = scan.shape
    sums: dict[str, tuple[_ErrorSums, _ErrorSums]] = {}
    step = max(1, METRIC_BAND_PIXELS // max(w, 1))
    for top in range(0, h, step):
        rows = slice(top, min(top + step, h))
        reference = scan.reference_depth[rows]
        raw, corrected = measured_depth(scan, correction, rows), correction.depth[rows]
        for region, where in metric_regions(scan, correction, rows).items():
            before, after = sums.setdefault(region, (_ErrorSums(), _ErrorSums()))
            before.add(raw[where], reference[where])
            after.add(corrected[where], reference[where])
    metrics = {}
    for region, (before, after) in sums.items():
        metrics[region] = {"pixels": before.rows, "raw_mae_m": before.mae_m(), "raw_rmse_m": before.rmse_m(),
                           "raw_max_abs_m": before.max_abs_m, "corrected_mae_m": after.mae_m(),
                           "corrected_rmse_m": after.rmse_m(), "corrected_max_abs_m": after.max_abs_m}
    return metrics


class _ErrorSums:
    """Running sums of the finite errors of estimates against a truth, band by band. [m]"""

    def __init__(self) -> None:
        self.rows, self.abs_sum, self.square_sum, self.max_abs_m = 0, 0.0, 0.0, float("nan")

    def add(self, estimate: np.ndarray, truth: np.ndarray) -> None:
        error = estimate.astype(np.float64)
        error -= truth
        error = np.abs(error[np.isfinite(error)])
        if error.size:
            self.rows += int(error.size)
            self.abs_sum += float(error.sum())
            self.square_sum += float(np.square(error).sum())
            self.max_abs_m = float(np.fmax(self.max_abs_m, error.max()))

    def mae_m(self) -> float:
        return self.abs_sum / self.rows if self.rows else float("nan")

    def rmse_m(self) -> float:
        return float(np.sqrt(self.square_sum / self.rows)) if self.rows else float("nan")


def applied_correction_mm(scan: Scan, correction: Correction) -> np.ndarray:
    """What correction did per pixel: corrected minus raw highest-frequency depth [mm], NaN where the pixel
    was not corrected (left as measured, or invalid)."""
    with np.errstate(invalid="ignore"):
        applied = 1e3 * (correction.depth.astype(np.float64) - measured_depth(scan, correction))
    return np.where(np.isin(correction.flags, MODEL_FLAGS), applied, np.nan)


def metrics_table(metrics: dict[str, dict[str, float]]) -> Table:
    """The metrics of :func:`scan_metrics` as a table, per region [mm]; a region without a pixel says so."""
    rows = []
    for region, m in metrics.items():
        if not m["pixels"]:
            rows.append((region, "0", *["no pixel"] * 6))
            continue
        rows.append((region, f"{m['pixels']:,}", f"{1e3 * m['raw_mae_m']:.3f}", f"{1e3 * m['corrected_mae_m']:.3f}",
                     f"{1e3 * m['raw_rmse_m']:.3f}", f"{1e3 * m['corrected_rmse_m']:.3f}",
                     f"{1e3 * m['raw_max_abs_m']:.2f}", f"{1e3 * m['corrected_max_abs_m']:.2f}"))
    return Table(("region", "pixels", "raw MAE [mm]", "corrected MAE [mm]", "raw RMSE [mm]", "corrected RMSE [mm]",
                  "raw max [mm]", "corrected max [mm]"), tuple(rows))
