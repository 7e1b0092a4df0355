"""The block planes judged against the scan's noise: a flat wall never faces itself at any range."""

from __future__ import annotations

import numpy as np
import pytest

from mpi_lidar.config import Config, SensorConfig
from mpi_lidar.correction import CorrectionOptions, analyse_geometry
from mpi_lidar.correction.scene import scene_blocks
from mpi_lidar.physics.noise import NoiseModel
from mpi_lidar.scans.geometry import fit_block_planes, plane_uncertainty, point_cloud, to_blocks
from mpi_lidar.scans.scan import Scan, grid_rays
from mpi_lidar.simulation.scenes import corner, flat_wall, render

pytestmark = pytest.mark.unit


def unwrapped_depth(scan: Scan, noise: NoiseModel) -> np.ndarray:
    """The highest frequency's unwrapped depth (H*W,) [m] of the pixels on a surface, NaN elsewhere."""
    f = len(scan.frequencies_hz)
    depth = noise.unwrap(scan.raw_pixels())[0][:, f - 1].astype(np.float64)
    depth[~np.isfinite(np.asarray(scan.reference_depth).ravel())] = np.nan
    return depth


@pytest.mark.parametrize("distance_m", [12.0, 20.0])
@pytest.mark.parametrize("noise_scale", [1.0, 2.5])
def test_flat_wall__no_block_faces_another_at_long_range(distance_m, noise_scale):
    config = Config().replace(simulator={"noise_scale": noise_scale})
    scan = render(flat_wall(0.0, distance_m, 0.7, height=48, width=64), config, np.random.default_rng(3))
    noise = NoiseModel.for_sensor(SensorConfig(), scan.frequencies_hz, noise_scale)
    depth = unwrapped_depth(scan, noise)
    scene = analyse_geometry(scan, depth, CorrectionOptions(), SensorConfig(), noise=noise)
    assert scene.blocks is not None and scene.blocks.pairs.a.size == 0
    assert scene.uncalibrated is None or scene.uncalibrated.mean() < 0.01
    given = analyse_geometry(scan, depth, CorrectionOptions(footprint_area_m2=0.04), SensorConfig(), noise=noise)
    assert given.reaches_min_bias is not None and not given.reaches_min_bias.any()


def test_corner__keeps_its_facing_pairs_under_the_noise():
    scan = render(corner(90.0, 2.0, 0.8, height=48, width=64), Config(), np.random.default_rng(0))
    noise = NoiseModel.for_sensor(SensorConfig(), scan.frequencies_hz)
    depth = unwrapped_depth(scan, noise)
    judged, residual_only = (scene_blocks(scan, depth, CorrectionOptions(), given) for given in (noise, None))
    assert judged is not None and residual_only is not None
    assert judged.pairs.a.size >= 0.95 * residual_only.pairs.a.size > 0


@pytest.mark.parametrize("noise_m", [0.002, 0.006])
def test_plane_uncertainty__predicts_the_spread_of_fitted_normals(noise_m):
    # 400 blocks of 6 x 6 pixels on the plane z = 3, 9 mm apart at the plane: the fitted normals' angles
    # from the true one scatter as the noise predicts (noise over spread about 0.13 and 0.38).
    b, blocks = 6, 400
    rays = grid_rays(np.arange(b) * 0.003, np.arange(b) * 0.003)
    rays = np.tile(rays, (1, blocks, 1))
    rng = np.random.default_rng(1)
    true_depth = 3.0 / rays[..., 2]
    depth = true_depth + rng.normal(0.0, noise_m, true_depth.shape)
    points = point_cloud(depth, rays)
    centres, normals, keep, usable, rms = fit_block_planes(points, b)
    sigma = to_blocks(np.full(depth.shape, noise_m), b)
    normal_sd, centre_sd = plane_uncertainty(to_blocks(points, b), keep, centres, normals, rms, sigma)
    assert usable.all() and np.isfinite(normal_sd).all()
    tilt = np.arccos(np.clip(np.abs(normals[..., 2]), -1.0, 1.0))  # 2-D angle: Rayleigh, rms sqrt(2) sd
    measured = np.sqrt(np.mean(tilt**2) / 2)
    assert np.median(normal_sd) == pytest.approx(measured, rel=0.25)
    assert np.median(centre_sd) == pytest.approx(noise_m / b, rel=0.1)


def test_plane_uncertainty__noise_as_wide_as_the_block_leaves_the_normal_unknown():
    b = 4
    rays = grid_rays(np.arange(b) * 0.003, np.arange(b) * 0.003)
    depth = 15.0 / rays[..., 2] + np.random.default_rng(2).normal(0.0, 0.06, (b, b))
    points = point_cloud(depth, rays)
    centres, normals, keep, _, rms = fit_block_planes(points, b)
    normal_sd, _ = plane_uncertainty(to_blocks(points, b), keep, centres, normals, rms,
                                     to_blocks(np.full((b, b), 0.06), b))
    assert np.isinf(normal_sd).all()
