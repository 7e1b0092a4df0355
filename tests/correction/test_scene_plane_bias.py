"""The partner planes' bias in the scene-geometry stage: light from surfaces the facing blocks do not see."""

from __future__ import annotations

import numpy as np
import pytest

from mpi_lidar.config import Config
from mpi_lidar.correction import CorrectionOptions, analyse_geometry
from mpi_lidar.correction.footprint import block_albedo, plane_model_inputs, unbent_planes
from mpi_lidar.simulation.scenes import flat_wall, render, room_with_box

pytestmark = pytest.mark.unit

MIN_BIAS_M = CorrectionOptions().min_multipath_bias_m


def usable_depth(scan) -> np.ndarray:
    return np.where(np.isfinite(scan.depth[-1]), scan.depth[-1], np.nan).ravel().astype(np.float32)


@pytest.fixture(scope="module")
def room():
    """A room corner (two walls, a floor, a box) at a strong footprint, with the render's true multipath bias (the
    light on coarser patches than the benchmark's, for time)."""
    truth: dict[str, np.ndarray] = {}
    scan = render(room_with_box(height=40, width=52, footprint_m2=0.073), Config(), np.random.default_rng(5),
                  truth_out=truth, patch_spacing_m=0.05)
    return scan, truth["bias_m"][:, -1]


@pytest.fixture(scope="module")
def room_scene(room):
    scan, _ = room
    return analyse_geometry(scan, usable_depth(scan), CorrectionOptions(footprint_area_m2=0.073), Config().sensor)


def blocks_alone(scene) -> tuple[np.ndarray, np.ndarray]:
    """The bias (H*W,) [m] the blocks alone give, and where it reaches the gate."""
    bias = scene.potential.bias_rows().ravel()
    return bias, bias >= MIN_BIAS_M


def test_analyse_geometry__room_pixels_the_blocks_miss_reach_the_gate(room, room_scene):
    _, true_bias = room
    _, block_reaches = blocks_alone(room_scene)
    added = room_scene.reaches_min_bias & ~block_reaches
    assert not (block_reaches & ~room_scene.reaches_min_bias).any()  # the planes only add
    # The room's walls light much of it from beyond the blocks' partner range: a third or more of the pixels with a
    # true bias over the threshold that the blocks leave alone now reach the gate, and nearly all that do carry it.
    missed = ~block_reaches & (true_bias >= MIN_BIAS_M)
    assert (added & missed).sum() >= 0.3 * missed.sum() > 100
    assert (added & missed).sum() >= 0.9 * added.sum()


def test_analyse_geometry__room_bias_map_is_the_larger_of_blocks_and_planes(room, room_scene):
    scan, true_bias = room
    block_bias, block_reaches = blocks_alone(room_scene)
    bias = room_scene.bias_m.ravel().astype(np.float64)
    assert np.all(np.abs(bias) >= block_bias.astype(np.float32))
    # Pixels the blocks already hand to the gate keep their bias; the others take the planes' where larger, as
    # PlaneModelInputs.bias_m gives it.
    np.testing.assert_array_equal(bias[block_reaches], block_bias[block_reaches].astype(np.float32))
    sensor, blocks = Config().sensor, room_scene.blocks
    planes = unbent_planes(scan, blocks, np.isfinite(usable_depth(scan)), sensor, 0.073,
                           surfaces=room_scene.surfaces, measured_albedo=block_albedo(scan, blocks, sensor))
    inputs = plane_model_inputs(scan, blocks, sensor, 0.073, room_scene.surfaces, fitted_planes=planes)
    pixels = np.flatnonzero(np.isfinite(usable_depth(scan)) & ~block_reaches)
    planes = inputs.bias_m(pixels, usable_depth(scan)[pixels].astype(np.float64), max(scan.frequencies_hz))
    expected = np.where(np.abs(planes) > block_bias[pixels], planes, block_bias[pixels]).astype(np.float32)
    np.testing.assert_allclose(bias[pixels], expected, rtol=1e-6, atol=1e-9)
    # Left alone by the blocks, the room's pixels are biased as the planes say (to a couple of mm), not as the
    # blocks say.
    left = pixels[np.isfinite(true_bias[pixels])]
    assert np.median(np.abs(bias[left] - true_bias[left])) < 0.5 * np.median(np.abs(block_bias[left] - true_bias[left]))


def test_analyse_geometry__plane_bias_does_not_depend_on_model_inputs_or_tiles(room, room_scene):
    scan, _ = room
    depth = usable_depth(scan)
    others = [analyse_geometry(scan, depth, CorrectionOptions(footprint_area_m2=0.073, tile_pixels=tile),
                               Config().sensor, with_model_inputs=inputs)
              for tile, inputs in ((262_144, True), (640, False))]
    for other in others:
        np.testing.assert_array_equal(other.bias_m, room_scene.bias_m)
        np.testing.assert_array_equal(other.reaches_min_bias, room_scene.reaches_min_bias)
    assert room_scene.model_inputs is None and others[0].model_inputs is not None


@pytest.mark.parametrize("footprint", ["auto", 0.041])
def test_analyse_geometry__flat_wall_keeps_the_blocks_bias_to_the_bit(footprint):
    scan = render(flat_wall(20.0, height=32, width=48), Config(), np.random.default_rng(1))
    scene = analyse_geometry(scan, usable_depth(scan), CorrectionOptions(footprint_area_m2=footprint),
                             Config().sensor)
    block_bias, block_reaches = blocks_alone(scene)
    assert scene.surfaces is None
    np.testing.assert_array_equal(scene.bias_m.ravel(), block_bias.astype(np.float32))
    np.testing.assert_array_equal(scene.reaches_min_bias, block_reaches)



def test_left_alone_bias__is_the_planes_where_they_set_the_bias_and_the_albedo_weighted_blocks_elsewhere(room):
    scan, _ = room
    scene = analyse_geometry(scan, usable_depth(scan), CorrectionOptions(), Config().sensor)
    assert scene.footprint is not None and scene.footprint.significant and scene.left_alone_potential is not None
    pixels = np.flatnonzero(np.isfinite(usable_depth(scan)))
    bias = scene.bias_m.ravel()[pixels].astype(np.float64)
    white = scene.potential.pixels(pixels).bias_m
    left_alone = scene.left_alone_bias_m(pixels)
    planes = np.abs(bias) > 1.001 * np.abs(white) + 1e-9
    assert planes.sum() > 100 and (~planes & (white > 0)).sum() > 100
    np.testing.assert_array_equal(left_alone[planes], bias[planes])
    np.testing.assert_allclose(left_alone[~planes], scene.left_alone_potential.pixels(pixels[~planes]).bias_m)
    assert np.all(np.abs(left_alone) <= np.abs(bias) * (1 + 1e-5) + 1e-12)  # the room's albedo, 0.7, is below 1
