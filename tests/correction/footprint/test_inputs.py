"""A geometric model's inputs from the partner planes (mpi_lidar.correction.footprint._inputs)."""

from __future__ import annotations

import numpy as np
import pytest

from mpi_lidar.config import Config
from mpi_lidar.correction.footprint import (
    PlaneModelInputs,
    block_albedo,
    plane_model_inputs,
    surface_labels,
    unbent_planes,
)
from mpi_lidar.scans.geometry import facing_blocks
from mpi_lidar.simulation.scenes import DEFAULT_FOOTPRINT_RADIUS_M, corner, flat_wall, render, room_with_box

pytestmark = pytest.mark.unit


def inputs_of(scene, area_m2: float) -> tuple[PlaneModelInputs, np.ndarray]:
    scan = render(scene, Config(), np.random.default_rng(1))
    depth = np.where(np.isfinite(scan.depth[-1]), scan.depth[-1], np.nan)
    blocks = facing_blocks(depth, scan.ray_rows())
    return plane_model_inputs(scan, blocks, Config().sensor, area_m2), depth.ravel()


def test_plane_model_inputs__a_corner_has_partners_and_a_flat_wall_none():
    inputs, depth = inputs_of(corner(90.0, 2.0, 0.8, height=32, width=64), 0.041)
    assert inputs.plane is not None
    rho_aba, d_ab = inputs.pixels(np.arange(depth.size), depth)
    assert (rho_aba > 0).any() and np.nanmax(d_ab) < 1.0
    wall, wall_depth = inputs_of(flat_wall(20.0, height=32, width=64), 0.041)
    assert wall.pixels(np.arange(wall_depth.size), wall_depth)[0].max() == 0.0
    assert np.all(wall.bias_m(np.arange(wall_depth.size), wall_depth, 31.25e6) == 0.0)


def test_plane_model_inputs__two_planes_have_no_two_bounce_light():
    """A -> B -> C -> A needs a third plane: a corner of two keeps its single bounces alone (the same inputs as
    without the two-bounce term)."""
    inputs, depth = inputs_of(corner(90.0, 2.0, 0.8, height=32, width=64), 0.041)
    assert inputs.plane is not None and len(inputs.plane.partners.partners) == 2
    assert inputs.plane.unit_bounces_at_blocks is None and inputs.two_bounce_phasor is None
    bias = inputs.bias_m(np.arange(depth.size), depth, 31.25e6)
    assert np.nanmax(bias) > 1e-3 and np.nanmin(bias) >= 0.0


def test_light_parts__sum_to_the_ratio_the_bias_rests_on_and_two_planes_have_no_light_among_partners():
    """The single bounces and the light among the partners add up to the one two-path ratio of the lowest frequency
    that :meth:`PlaneModelInputs.bias_m` turns into a bias: its phase is that bias there."""
    config = Config()
    lowest = min(config.frequencies_hz)
    metres_per_rad = config.sensor.speed_of_light_m_per_s / (4 * np.pi * lowest)
    for scene, three in ((room_with_box(height=48, width=64), True), (corner(90.0, 2.0, 0.8, height=32, width=64),
                                                                     False)):
        inputs, depth = inputs_of(scene, 0.073)
        pixels = np.flatnonzero(np.isfinite(depth))
        single, among = inputs.light_parts(pixels, depth[pixels])
        lit = np.abs(single + among) > 0
        assert lit.sum() > 100
        np.testing.assert_allclose(np.angle(1.0 + single[lit] + among[lit]) * metres_per_rad,
                                   inputs.bias_m(pixels, depth[pixels], lowest)[lit], atol=1e-9)
        assert (np.abs(among[lit]) > 0.01 * np.abs(single[lit])).any() == three


def test_plane_model_inputs__at_zero_footprint_the_blocks_estimate_of_no_multipath():
    inputs, depth = inputs_of(corner(90.0, 2.0, 0.8, height=32, width=64), 0.0)
    assert inputs.plane is None
    assert inputs.pixels(np.arange(depth.size), depth)[0].max() == 0.0


@pytest.mark.parametrize("angle_deg, area_m2", [(90.0, 0.073), (90.0, 0.163), (60.0, 0.073)])
def test_unbent_planes__the_inputs_read_the_renders_coupling_where_the_blocks_planes_overstate_it(angle_deg, area_m2):
    # Multipath lengthens each board's depths towards the edge, so the planes through the blocks meet too
    # sharply and the equivalent rho_ABA reads 1.15-1.5x the render's (more at a larger footprint); the planes
    # fitted to the least-coupled pixels less their bias read it to within 10 %.
    truth: dict[str, np.ndarray] = {}
    scan = render(corner(angle_deg, 2.0, 0.8), Config(), np.random.default_rng(0),
                  coupling_gain=area_m2 / (np.pi * DEFAULT_FOOTPRINT_RADIUS_M**2), truth_out=truth)
    depth = np.where(np.isfinite(scan.reference_depth), scan.depth[-1], np.nan)
    blocks, sensor = facing_blocks(depth, scan.ray_rows()), Config().sensor
    surfaces, albedo = surface_labels(blocks), block_albedo(scan, blocks, sensor)
    planes = unbent_planes(scan, blocks, np.isfinite(depth).ravel(), sensor, area_m2, surfaces=surfaces,
                           measured_albedo=albedo)
    assert len(planes) == 2  # both boards
    strong = np.flatnonzero(np.isfinite(depth).ravel() & (truth["bias_m"][:, -1] > 4e-3))

    def read_over_true(fitted):
        inputs = plane_model_inputs(scan, blocks, sensor, area_m2, surfaces, albedo, fitted_planes=fitted)
        rho_aba = inputs.pixels(strong, depth.ravel()[strong].astype(np.float64))[0]
        return float(np.median(rho_aba / truth["rho_aba"][strong]))

    assert read_over_true(None) > 1.1
    assert 0.9 <= read_over_true(planes) <= 1.1


def test_unbent_planes__nothing_facing_or_no_footprint_has_none():
    scan = render(corner(90.0, 2.0, 0.8, height=32, width=64), Config(), np.random.default_rng(1))
    depth = np.where(np.isfinite(scan.depth[-1]), scan.depth[-1], np.nan)
    blocks, sensor = facing_blocks(depth, scan.ray_rows()), Config().sensor
    for area in (0.0, float("nan")):
        assert unbent_planes(scan, blocks, np.isfinite(depth).ravel(), sensor, area, surfaces=surface_labels(blocks),
                             measured_albedo=block_albedo(scan, blocks, sensor)) == {}
    wall = render(flat_wall(20.0, height=32, width=64), Config(), np.random.default_rng(1), patch_spacing_m=1.0)
    wall_depth = np.where(np.isfinite(wall.depth[-1]), wall.depth[-1], np.nan)
    wall_blocks = facing_blocks(wall_depth, wall.ray_rows())
    wall_albedo = block_albedo(wall, wall_blocks, sensor)
    assert unbent_planes(wall, wall_blocks, np.isfinite(wall_depth).ravel(), sensor, 0.041,
                         surfaces=surface_labels(wall_blocks), measured_albedo=wall_albedo) == {}
