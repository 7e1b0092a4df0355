"""Errors per band of the true range, and the range benchmark's quick run."""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest

from mpi_lidar.errors import MpiLidarError
from mpi_lidar.learning.range_bands import RANGE_BANDS_M, range_band_errors


@pytest.mark.unit
def test_range_band_errors__hand_computed_band_values():
    truth = np.array([0.6, 0.9, 1.5, 1.7, 1.9])
    raw = truth + np.array([0.010, 0.020, 0.030, 0.040, 0.050])
    limit = truth + np.array([0.002, -0.004, 0.006, -0.003, 0.003])
    model = truth + np.array([-0.004, 0.004, 0.006, 0.006, -0.006])
    near, middle, *rest = range_band_errors(truth, raw, limit, model)
    assert (near.band_m, near.rows, middle.rows) == ((0.5, 1.0), 2, 3)
    assert near.raw_mae_m == pytest.approx(0.015, abs=1e-15)
    assert near.limit_mae_m == pytest.approx(0.003, abs=1e-15) and near.model_mae_m == pytest.approx(0.004, abs=1e-15)
    assert near.limit_se_m == pytest.approx(np.std([0.002, 0.004], ddof=1) / np.sqrt(2), abs=1e-15)
    assert near.model_se_m == pytest.approx(0.0, abs=1e-15)
    assert near.ratio == pytest.approx(4 / 3, rel=1e-12)
    # delta method: sd(m_i - r l_i) / (sqrt(n) mean(l)) with m = (4, 4), l = (2, 4) mm, r = 4/3
    residual = np.array([4 - 4 / 3 * 2, 4 - 4 / 3 * 4]) * 1e-3
    assert near.ratio_se == pytest.approx(residual.std(ddof=1) / (np.sqrt(2) * 0.003), rel=1e-12)
    assert middle.ratio == pytest.approx(0.018 / 0.012, rel=1e-12)
    assert all(band.rows == 0 and np.isnan(band.limit_mae_m) and np.isnan(band.ratio) for band in rest)


@pytest.mark.unit
def test_range_band_errors__a_model_twice_the_limit_has_ratio_two_known_exactly():
    rng = np.random.default_rng(3)
    truth = rng.uniform(0.5, 12.0, 1_000)
    limit_error = rng.normal(0, 0.01, 1_000)
    found = range_band_errors(truth, truth, truth + limit_error, truth - 2 * limit_error)
    for band in found:
        assert band.ratio == pytest.approx(2.0, rel=1e-12)
        assert band.ratio_se == pytest.approx(0.0, abs=1e-12)  # paired rows: no sampling noise in the ratio
    assert sum(band.rows for band in found) == 1_000


@pytest.mark.unit
def test_range_band_errors__last_band_includes_its_end_and_rows_outside_every_band_are_left_out():
    truth = np.array([0.4, 0.5, 1.0, 12.0, 12.5])
    found = range_band_errors(truth, truth, truth, None)
    assert [band.rows for band in found] == [1, 1, 0, 0, 1]
    assert all(np.isnan(band.model_mae_m) and np.isnan(band.ratio) for band in found)
    assert [band.rows for band in range_band_errors(truth, truth, truth, None, ((0.5, 1.0),))] == [2]


@pytest.mark.unit
def test_range_band_errors__refuses_columns_of_another_length():
    with pytest.raises(MpiLidarError, match=r"posterior_median_m must have one value per row, shape \(3,\)"):
        range_band_errors(np.ones(3), np.ones(3), np.ones(2), np.ones(3))
    assert RANGE_BANDS_M[0] == (0.5, 1.0) and RANGE_BANDS_M[-1] == (8.0, 12.0)


@pytest.mark.integration
@pytest.mark.slow
def test_range_bands_benchmark__quick_run_prints_every_band():
    done = subprocess.run([sys.executable, "-m", "benchmarks.range_bands", "--quick"], capture_output=True,
                          text=True, check=False, timeout=300)
    assert done.returncode == 0, done.stderr
    rows = [line for line in done.stdout.splitlines() if line.startswith("| ") and "true d_AS" not in line]
    assert [row.split(" | ")[0].removeprefix("| ") for row in rows] == ["0.5-1", "1-2", "2-4", "4-8", "8-12", "0.5-12"]
    assert all(row.count("±") == 4 for row in rows)  # the limit and the three models' ratios have a standard error
