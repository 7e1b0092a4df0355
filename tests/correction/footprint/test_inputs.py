"""A geometric model's inputs from the partner planes (mpi_lidar.correction.footprint._inputs)."""

from __future__ import annotations

import numpy as np
import pytest

from mpi_lidar.config import Config
from mpi_lidar.correction.footprint import PlaneModelInputs, plane_model_inputs
from mpi_lidar.scans.geometry import facing_blocks
from mpi_lidar.simulation.scenes import corner, flat_wall, render

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


def test_plane_model_inputs__at_zero_footprint_the_blocks_estimate_of_no_multipath():
    inputs, depth = inputs_of(corner(90.0, 2.0, 0.8, height=32, width=64), 0.0)
    assert inputs.plane is None
    assert inputs.pixels(np.arange(depth.size), depth)[0].max() == 0.0
