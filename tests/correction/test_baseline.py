"""The baseline's frequency offsets: a profile's, the scan's own on pixels free of multipath, or none."""

from __future__ import annotations

import numpy as np
import pytest

from mpi_lidar.config import PAPER_FREQUENCIES_HZ, SensorConfig
from mpi_lidar.correction.baseline import (
    MIN_OFFSET_PIXELS,
    QUIET_BIAS_M,
    FrequencyOffsets,
    OffsetSource,
    frequency_offsets,
    fuse_rows,
)
from mpi_lidar.correction.options import CorrectionOptions, Flag
from mpi_lidar.correction.validity import OffsetSample
from mpi_lidar.physics.noise import NoiseModel

pytestmark = pytest.mark.unit

OFFSETS_M = np.array([0.0012, -0.0004, 0.0003, 0.0])


def _sample(pixels: int, window_shift_m: float = 0.0) -> OffsetSample:
    """A sample of ``pixels`` whose frequencies read OFFSETS_M apart (plus noise), the window's leakage
    shifting them by ``window_shift_m`` more at the lowest frequency."""
    sample = OffsetSample.empty(pixels, 4)
    noise = np.random.default_rng(0).normal(0, 1e-4, sample.differences.shape)
    sample.differences[:] = OFFSETS_M + noise
    sample.window_differences[:] = OFFSETS_M + noise + np.array([window_shift_m, 0, 0, 0])
    return sample


def test_frequency_offsets__the_median_of_the_quiet_sampled_pixels():
    flags = np.full(5000, Flag.NO_MULTIPATH, np.uint8)
    bias = np.zeros(5000)
    found = frequency_offsets(_sample(5000, window_shift_m=0.001), flags, bias, CorrectionOptions())
    assert found.source == OffsetSource.MEASURED and not found.window, "removing the leakage would widen them"
    np.testing.assert_allclose(found.offsets_m, OFFSETS_M, atol=1e-5)
    np.testing.assert_allclose(found.other_m, OFFSETS_M + np.array([0.001, 0, 0, 0]), atol=1e-5)
    shrinking = frequency_offsets(_sample(5000, window_shift_m=-0.0012), flags, bias, CorrectionOptions())
    assert shrinking.window and abs(shrinking.offsets_m[0]) < 1e-4


def test_frequency_offsets__corrected_or_multipath_pixels_are_not_quiet_and_too_few_measure_nothing():
    flags = np.full(5000, Flag.CORRECTED, np.uint8)
    flags[: MIN_OFFSET_PIXELS - 1] = Flag.NOT_NEEDED
    bias = np.zeros(5000)
    assert frequency_offsets(_sample(5000), flags, bias, CorrectionOptions()).source == OffsetSource.TOO_FEW_PIXELS
    flags[:] = Flag.NO_MULTIPATH
    bias[:] = 2 * QUIET_BIAS_M
    assert frequency_offsets(_sample(5000), flags, bias, CorrectionOptions()).offsets_m is None


def test_frequency_offsets__a_profile_gives_them_the_raw_baseline_needs_none_no_geometry_measures_none():
    flags, bias = np.full(5000, Flag.NO_MULTIPATH, np.uint8), np.zeros(5000)
    given = CorrectionOptions(frequency_offsets_m=(0.001, 0.0, 0.0, 0.0), window_leakage_removed=True)
    profile = frequency_offsets(_sample(5000), flags, bias, given)
    assert profile.source == OffsetSource.PROFILE and profile.window and profile.offsets_m[0] == 0.001
    assert frequency_offsets(_sample(5000), flags, bias, CorrectionOptions(baseline="raw")) == FrequencyOffsets()
    assert frequency_offsets(_sample(5000), flags, None, CorrectionOptions()).source == OffsetSource.NO_GEOMETRY


def test_fuse_rows__removes_the_offsets_before_fusing():
    noise = NoiseModel.for_sensor(SensorConfig(), PAPER_FREQUENCIES_HZ)
    raw = np.hstack([np.full((3, 4), 2.0) + OFFSETS_M, np.full((3, 4), 0.01)])
    fused = fuse_rows(raw, noise, FrequencyOffsets(OFFSETS_M, False, OffsetSource.PROFILE))
    np.testing.assert_allclose(fused.depth_m, 2.0, atol=1e-6)
    assert fused.consistent.all()
