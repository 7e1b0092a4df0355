"""The scan in memory (mpi_lidar.scans.scan): rays, validation against the declared variables, taps."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from mpi_lidar.config import Config
from mpi_lidar.constants import TABLE_SPEED_OF_LIGHT_M_PER_S
from mpi_lidar.physics.demod import taps_from_quadratures
from mpi_lidar.scans.scan import ScanError, from_taps, grid_rays, scan_extras, validate
from tests.scan_factory import two_path_scan

pytestmark = pytest.mark.unit

FREQS = Config().frequencies_hz


def test_grid_rays__unit_vectors_along_the_documented_axes():
    rays = grid_rays(np.array([0.0, np.pi / 2]), np.array([0.0, np.pi / 2]))
    np.testing.assert_allclose(np.linalg.norm(rays, axis=-1), 1.0)
    np.testing.assert_allclose(rays[0, 0], [0, 0, 1], atol=1e-12)  # forward
    np.testing.assert_allclose(rays[0, 1], [1, 0, 0], atol=1e-12)  # right
    np.testing.assert_allclose(rays[1, 0], [0, 1, 0], atol=1e-12)  # up


@pytest.mark.parametrize(("change", "message"), [
    ({"reference_mask": np.ones((24, 32), np.float32)},
     r"^s: reference_mask must be boolean, got float32; store it as bool \(True where the reference holds\)$"),
    ({"azimuth_rad": np.arange(32)}, r"^s: azimuth_rad must be floating point, got int64$"),
    ({"taps": np.zeros((4, 4, 24, 32), np.int16)}, r"^s: taps must be floating point, got int16$"),
    ({"ray_directions": np.zeros((24, 32, 2), np.float32)}, r"ray_directions must have shape \(24, 32, 3\)"),
])
def test_validate__arrays_of_another_dtype_or_shape_than_declared_are_one_error(change, message):
    with pytest.raises(ScanError, match=message):
        validate(replace(two_path_scan("s"), **change), "s")


def test_validate__the_boolean_mask_is_checked_before_the_other_dtypes():
    scan = replace(two_path_scan("s"), azimuth_rad=np.arange(32), reference_mask=np.ones((24, 32), np.uint8))
    with pytest.raises(ScanError, match="reference_mask must be boolean"):
        validate(scan, "s")


def test_from_taps__keeps_the_extras_and_the_scene():
    scan = two_path_scan("t", height=5, width=6)
    rng = np.random.default_rng(0)
    phase, gamma = rng.uniform(0.1, 6.0, (4, 5, 6)), rng.uniform(0.01, 0.05, (4, 5, 6))
    taps = np.moveaxis(taps_from_quadratures(gamma * np.cos(phase), gamma * np.sin(phase)), -1, 1)
    extras = scan_extras({"azimuth_rad": scan.azimuth_rad, "elevation_rad": scan.elevation_rad, "taps": taps})
    assert set(extras) == {"azimuth_rad", "elevation_rad", "ray_directions", "reference_depth", "reference_mask"}
    made = from_taps("t", FREQS, taps, TABLE_SPEED_OF_LIGHT_M_PER_S, scene={"kind": "test"}, **extras)
    assert made.scene == {"kind": "test"} and made.taps is not None and made.ray_directions is None
    np.testing.assert_array_equal(made.azimuth_rad, scan.azimuth_rad)
    assert from_taps("t", FREQS, taps, TABLE_SPEED_OF_LIGHT_M_PER_S).scene == {}
