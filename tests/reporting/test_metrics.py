"""Errors of a corrected scan against its reference depth, per region, summed a band of rows at a time."""

from __future__ import annotations

import numpy as np
import pytest

from mpi_lidar.correction import Correction, Flag
from mpi_lidar.reporting import metrics
from mpi_lidar.reporting.metrics import metrics_table, scan_metrics
from tests.scan_factory import two_path_scan

pytestmark = pytest.mark.unit


def _correction(scan) -> Correction:
    flags = np.full(scan.shape, int(Flag.NO_MULTIPATH), np.uint8)
    flags[:, : scan.shape[1] // 2] = Flag.CORRECTED
    flags[0, 0] = Flag.NOT_FINITE
    depth = scan.depth[-1] - 0.003 * (flags == Flag.CORRECTED)
    return Correction(depth=depth.astype(np.float32), flags=flags, inference_s=0.0, total_s=0.0)


def test_scan_metrics__bands_of_rows_sum_to_the_whole_scan(monkeypatch):
    scan = two_path_scan("measured")
    correction = _correction(scan)
    whole = scan_metrics(scan, correction)
    monkeypatch.setattr(metrics, "METRIC_BAND_PIXELS", scan.shape[1] * 5)  # five rows a band, the last shorter
    banded = scan_metrics(scan, correction)
    assert set(whole) == {"whole map", "masked region"} and whole["whole map"]["pixels"] == scan.depth[-1].size - 1
    for region, values in whole.items():
        assert banded[region] == pytest.approx(values, rel=1e-12)
    error = np.abs(correction.depth.astype(np.float64) - scan.reference_depth).ravel()[1:]
    assert whole["whole map"]["corrected_mae_m"] == pytest.approx(error.mean(), rel=1e-9)
    assert metrics_table(whole).headers[:3] == ("region", "pixels", "raw MAE [mm]")


def test_metrics_table__a_region_without_a_pixel_says_so_not_nan():
    scan = two_path_scan("dark")
    flags = np.full(scan.shape, int(Flag.NO_RETURN), np.uint8)
    empty = scan_metrics(scan, Correction(depth=np.full(scan.shape, np.nan, np.float32), flags=flags,
                                          inference_s=0.0, total_s=0.0))
    assert empty["whole map"]["pixels"] == 0
    rows = metrics_table(empty).rows
    assert rows[0][:3] == ("whole map", "0", "no pixel") and not any("nan" in cell for row in rows for cell in row)
