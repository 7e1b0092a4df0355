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


def _blocks(scene, pixels: int):
    """The facing blocks of a render of ``scene`` of ``pixels`` pixels (50 x 100)."""
    from mpi_lidar.config import Config
    from mpi_lidar.correction.scene import scene_blocks
    from mpi_lidar.simulation.scenes import render

    scan = render(scene, Config(), np.random.default_rng(0))
    assert scan.shape[0] * scan.shape[1] == pixels
    return scene_blocks(scan, scan.depth[-1].ravel().astype(np.float64), CorrectionOptions())


@pytest.fixture(scope="module")
def wall_blocks():
    from mpi_lidar.simulation.scenes import flat_wall

    return _blocks(flat_wall(10.0, 2.0, 0.7, height=50, width=100), 5000)


@pytest.fixture(scope="module")
def corner_blocks():
    from mpi_lidar.simulation.scenes import corner

    return _blocks(corner(60.0, 2.0, 0.8, height=50, width=100), 5000)


def test_frequency_offsets__the_median_of_the_quiet_sampled_pixels(wall_blocks):
    flags = np.full(5000, Flag.NO_MULTIPATH, np.uint8)
    bias = wall_blocks
    found = frequency_offsets(_sample(5000, window_shift_m=0.001), flags, bias, CorrectionOptions())
    assert found.source == OffsetSource.MEASURED and not found.window, "removing the leakage would widen them"
    np.testing.assert_allclose(found.offsets_m, OFFSETS_M, atol=1e-5)
    np.testing.assert_allclose(found.other_m, OFFSETS_M + np.array([0.001, 0, 0, 0]), atol=1e-5)
    shrinking = frequency_offsets(_sample(5000, window_shift_m=-0.0012), flags, bias, CorrectionOptions())
    assert shrinking.window and abs(shrinking.offsets_m[0]) < 1e-4


def test_frequency_offsets__corrected_or_multipath_pixels_are_not_quiet_and_too_few_measure_nothing(
        wall_blocks, corner_blocks):
    flags = np.full(5000, Flag.CORRECTED, np.uint8)
    flags[: MIN_OFFSET_PIXELS - 1] = Flag.NOT_NEEDED
    found = frequency_offsets(_sample(5000), flags, wall_blocks, CorrectionOptions())
    assert found.source == OffsetSource.TOO_FEW_PIXELS
    flags[:] = Flag.NO_MULTIPATH
    # a sharp corner: most pixels face the other wall, so fewer pixels are quiet than on a wall
    from mpi_lidar.physics.coupling import DEFAULT_FOOTPRINT_AREA_M2

    bias = corner_blocks.block_potential(DEFAULT_FOOTPRINT_AREA_M2).pixels(np.arange(5000)).bias_m
    assert (bias > QUIET_BIAS_M).mean() > 0.5
    assert frequency_offsets(_sample(5000), flags, wall_blocks, CorrectionOptions()).offsets_m is not None


def test_frequency_offsets__a_profile_gives_them_the_raw_baseline_needs_none_no_geometry_measures_none(wall_blocks):
    flags, bias = np.full(5000, Flag.NO_MULTIPATH, np.uint8), wall_blocks
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
