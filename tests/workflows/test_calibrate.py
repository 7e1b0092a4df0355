"""What ``mpi-lidar calibrate`` pools (mpi_lidar.workflows.calibrate): the scans' sensor scales, with and without
the integration window's leakage."""

from __future__ import annotations

import numpy as np
import pytest

from mpi_lidar.calibration import SensorScale
from mpi_lidar.workflows.calibrate import pool_scales

pytestmark = pytest.mark.unit


def test_pool_scales__keeps_the_leakage_removed_where_that_leaves_smaller_offsets():
    def scale(offsets_m):
        return SensorScale(4000.0, 40.0, 1.0, 0.0, np.array(offsets_m), np.full(4, 2e-5), 5000, True, "")

    leaking, left = scale([-4e-4, -2.4e-4, -1e-4, 0.0]), scale([1e-5, -1e-5, 0.0, 0.0])
    pooled = pool_scales([leaking, leaking], [left, left])
    assert pooled["window_leakage_removed"] is True
    np.testing.assert_allclose(pooled["frequency_offsets_m"], left.offsets_m)
    reversed_ = pool_scales([left, left], [leaking, leaking])
    assert reversed_["window_leakage_removed"] is False
    np.testing.assert_allclose(reversed_["frequency_offsets_m"], left.offsets_m)
    assert "window_leakage_removed" not in pool_scales([leaking])


def test_pool_scales__weighs_each_scan_by_its_inverse_variance_and_skips_the_insignificant():
    def scale(units, sigma, noise, noise_sigma, significant=True):
        return SensorScale(units, sigma, noise, noise_sigma, np.zeros(4), np.full(4, 1e-5), 5000, significant, "")

    pooled = pool_scales([scale(4000.0, 40.0, 1.0, 0.01), scale(4400.0, 80.0, 1.2, 0.02),
                          scale(1.0, 0.1, 9.0, 0.1, significant=False)])
    # Log scales weighted by (scale / sigma)^2: 10^4 and 3025.
    expected = np.exp(np.average(np.log([4000.0, 4400.0]), weights=[1e4, 3025.0]))
    assert pooled["amplitude_scale"] == pytest.approx(expected, rel=1e-12)
    assert 1.0 < pooled["noise_scale"] < 1.1 and pooled["frequency_offsets_m"] == (0.0, 0.0, 0.0, 0.0)
    assert pool_scales([scale(1.0, 0.1, 9.0, 0.1, significant=False)]) == {}
    # A noise scale held fixed (sigma 0) says nothing of the noise.
    assert "noise_scale" not in pool_scales([scale(4000.0, 40.0, 1.0, 0.0)])
