"""Flat-surface residuals (mpi_lidar.calibration.flat_residuals): against noiseless renders, the planes' own
leverages and the renderer's own multipath."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from mpi_lidar.calibration.flat_residuals import MAX_PIXELS, FlatSurfaceResiduals, flat_surface_residuals
from mpi_lidar.correction import CorrectionOptions
from mpi_lidar.correction.scene import scene_blocks
from mpi_lidar.simulation.scenes import corner, flat_wall
from tests.calibration.rendered_scenes import boards_scene, depth_usable, rendered

pytestmark = pytest.mark.unit


def test_flat_surface_residuals__noiseless_planes_leave_nothing_on_the_boards():
    scan = rendered(boards_scene(), noise_scale=0.0, whole_cycles=True, round_photons=False)
    flat = flat_surface_residuals(scan, depth_usable(scan), CorrectionOptions())
    assert flat.residual_m.shape == (flat.pixels.size, 4) and flat.amplitude.shape == flat.residual_m.shape
    assert flat.pixels.size > 15_000 and flat.blocks > 600
    # The planes are exact, the window whole: what is left (float32 depths, the boards' faint light on each other) is
    # a few micrometres, against millimetres of noise.
    assert np.abs(flat.residual_m).max() < 5e-6
    # No pixel near an edge: each lies on a board with its 3 x 3 neighbourhood (the render's reference mask).
    assert scan.reference_mask.ravel()[flat.pixels].all()
    np.testing.assert_array_equal(flat.amplitude, scan.amplitude.reshape(4, -1).T[flat.pixels])


def test_flat_surface_residuals__the_leverages_of_a_block_sum_to_the_planes_three_parameters():
    scan = rendered(boards_scene())
    flat = flat_surface_residuals(scan, depth_usable(scan), CorrectionOptions())
    blocks = scene_blocks(scan, depth_usable(scan), CorrectionOptions())
    assert blocks is not None
    b, (_, width) = blocks.block_pixels, scan.shape
    row, column = np.divmod(flat.pixels, width)
    block = (row // b) * blocks.usable.shape[1] + column // b
    _, inverse, counts = np.unique(block, return_inverse=True, return_counts=True)
    sums = np.bincount(inverse, flat.leverage)
    whole = counts == b * b
    assert whole.sum() > 300 and np.unique(block).size == flat.blocks
    # Where the robust fit kept every pixel, the hat matrix's trace: 3; a pixel it trimmed adds a prediction's.
    assert np.median(sums[whole]) == pytest.approx(3.0, abs=1e-9)
    assert (sums[whole] >= 3.0 - 1e-9).all()


def test_flat_surface_residuals__no_pixel_within_the_partner_range_of_a_corner():
    truth: dict[str, np.ndarray] = {}
    scene = corner(90.0, 1.6, 0.8, height=48, width=160, board_m=1.2, half_height_m=0.5)
    scene = dataclasses.replace(scene, azimuth_rad=np.linspace(-0.7, 0.7, 160))
    scan = rendered(scene, truth_out=truth, patch_spacing_m=0.05)
    options = CorrectionOptions()
    flat = flat_surface_residuals(scan, depth_usable(scan), options)
    bias = np.abs(truth["bias_m"]).max(1)
    assert bias.max() > 0.01 and (bias > 1e-3).mean() > 0.3  # a scene with strong multipath
    assert flat.pixels.size > 500  # the boards' far ends
    # Every pixel taken lies beyond the partner range from the corner line (x = 0, z = 1.6 m), less a block or two
    # (blocks pair by their centres).
    points = scan.reference_depth.ravel()[flat.pixels, None] * scan.rays().reshape(-1, 3)[flat.pixels]
    from_edge_m = np.hypot(points[:, 0], points[:, 2] - 1.6)
    assert from_edge_m.min() > options.partner_range_m - 0.1
    # What the partner range leaves out: the far board still sends some multipath, under 1 mm (16 mm at the edge).
    assert bias[flat.pixels].max() < 1e-3


def test_flat_surface_residuals__a_scan_without_geometry_has_none():
    scan = rendered(boards_scene())
    bare = dataclasses.replace(scan, azimuth_rad=None, elevation_rad=None)
    flat = flat_surface_residuals(bare, depth_usable(bare), CorrectionOptions())
    assert flat.pixels.size == 0 and flat.residual_m.shape == (0, 4) and flat.blocks == 0


def test_flat_surface_residuals__a_pixel_off_the_plane_takes_its_eight_neighbours_with_it():
    scan = rendered(flat_wall(height=48, width=64))
    options = CorrectionOptions()
    before = flat_surface_residuals(scan, depth_usable(scan), options)
    y, x = 20, 30
    depth = scan.depth.copy()
    depth[:, y, x] += 0.3  # a flying pixel: 30 cm off the wall in every frequency
    spiked = dataclasses.replace(scan, depth=depth)
    after = flat_surface_residuals(spiked, depth_usable(spiked), options)
    # An edge's mixed pixels: the pixel leaves by its distance from the plane, its neighbours by being beside it;
    # nothing else of the wall moves.
    width = scan.shape[1]
    neighbourhood = {(y + dy) * width + x + dx for dy in (-1, 0, 1) for dx in (-1, 0, 1)}
    assert set(before.pixels) - set(after.pixels) == neighbourhood & set(before.pixels)
    assert len(neighbourhood & set(before.pixels)) >= 6 and set(after.pixels) <= set(before.pixels)


def test_flat_surface_residuals__max_pixels_takes_whole_blocks_evenly():
    scan = rendered(flat_wall(height=48, width=64))
    usable = depth_usable(scan)
    every = flat_surface_residuals(scan, usable, CorrectionOptions())
    blocks = scene_blocks(scan, usable, CorrectionOptions())
    assert blocks is not None and every.pixels.size < MAX_PIXELS
    per_block = blocks.block_pixels**2
    few = flat_surface_residuals(scan, usable, CorrectionOptions(), max_pixels=500)
    assert few.blocks == 500 // per_block and few.pixels.size <= 500
    assert set(few.pixels) <= set(every.pixels)
    rows = np.isin(every.pixels, few.pixels)
    np.testing.assert_array_equal(few.residual_m, every.residual_m[rows])  # the same planes, block by block
    # Spread over the wall: the blocks taken span its rows.
    block_rows = few.pixels // scan.shape[1] // blocks.block_pixels
    assert block_rows.max() - block_rows.min() >= blocks.usable.shape[0] - 3


def test_flat_surface_residuals__is_frozen():
    scan = rendered(flat_wall(height=48, width=64))
    flat = flat_surface_residuals(scan, depth_usable(scan), CorrectionOptions())
    assert isinstance(flat, FlatSurfaceResiduals)
    with pytest.raises(dataclasses.FrozenInstanceError):
        flat.blocks = 0  # type: ignore[misc]
