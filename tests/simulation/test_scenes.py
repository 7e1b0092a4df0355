from __future__ import annotations

import numpy as np
import pytest

from mpi_lidar.config import Config
from mpi_lidar.physics.transport import two_path_phase_bias
from mpi_lidar.scans.scan import grid_rays
from mpi_lidar.scans.store import read_scan, write_scan
from mpi_lidar.simulation.scenes import (
    DEFAULT_FOOTPRINT_RADIUS_M,
    Cylinder,
    Rectangle,
    Scene,
    Sphere,
    alcove,
    box_on_floor,
    corner,
    cornered_board,
    first_hits,
    flat_wall,
    floor_meets_wall,
    light_transport,
    pitch_rotation,
    render,
    room_corner,
    scan_from_phasors,
    scan_from_transient,
)

NOISELESS = Config().replace(simulator={"noise_scale": 0, "whole_cycles": True, "round_photons": False})
FREQS = np.asarray(Config().frequencies_hz)
C = 3e8


@pytest.mark.unit
def test_rectangle_intersect__distance_to_a_tilted_plane_matches_closed_form():
    wall = Rectangle((0.0, 0.0, 2.0), (1.0, 0.0, 0.5), (0.0, 1.0, 0.0))
    rays = grid_rays(np.linspace(-0.2, 0.2, 5), np.linspace(-0.1, 0.1, 3)).reshape(-1, 3)
    t = wall.intersect(np.zeros_like(rays), rays)
    normal = np.cross([1.0, 0.0, 0.5], [0.0, 1.0, 0.0])
    np.testing.assert_allclose(t, (normal @ [0, 0, 2.0]) / (rays @ normal), rtol=1e-12)


@pytest.mark.unit
def test_sphere_intersect__front_surface_and_outward_normal():
    ball = Sphere((0.0, 0.0, 3.0), 0.5)
    t = ball.intersect(np.zeros((2, 3)), np.array([[0.0, 0.0, 1.0], [0.0, 1.0, 0.0]]))
    assert t[0] == pytest.approx(2.5) and np.isinf(t[1])
    np.testing.assert_allclose(ball.normal_at(np.array([[0.0, 0.0, 2.5]])), [[0.0, 0.0, -1.0]])


@pytest.mark.unit
def test_cylinder_intersect__side_hit_within_height_only():
    pole = Cylinder((0.0, -1.0, 2.0), 0.25, 2.0)
    t = pole.intersect(np.zeros((2, 3)), np.array([[0.0, 0.0, 1.0], [0.0, 0.8, 0.6]]))
    assert t[0] == pytest.approx(1.75)
    assert np.isinf(t[1])  # passes above the top


@pytest.mark.unit
def test_render__flat_wall_noiseless_is_exact_and_amplitude_is_lambertian():
    scene = flat_wall(tilt_deg=20, height=12, width=16)
    scan = render(scene, NOISELESS, np.random.default_rng(0))
    np.testing.assert_allclose(scan.depth, np.broadcast_to(scan.reference_depth, scan.depth.shape), atol=1e-5)
    rays = grid_rays(scene.azimuth_rad, scene.elevation_rad)
    normal = np.array([-np.sin(np.deg2rad(20)), 0.0, np.cos(np.deg2rad(20))])  # facing the scanner: -normal
    cos_i = np.abs(rays @ normal)
    expected = 0.1794 * 0.7 * cos_i / scan.reference_depth.astype(np.float64) ** 2
    np.testing.assert_allclose(scan.amplitude[-1], expected, rtol=1e-4)
    assert scan.reference_mask[1:-1, 1:-1].all()


@pytest.mark.unit
def test_render__corner_bias_is_positive_and_falls_away_from_the_edge():
    scene = corner(90.0, 2.0, 0.8, height=8, width=64)
    scan = render(scene, NOISELESS, np.random.default_rng(0))
    bias = (scan.depth[-1] - scan.reference_depth)[4]
    right = bias[33:]  # from the edge outwards on the right board
    assert (right > 0).all(), "multipath only lengthens the path"
    assert right[1] > right[10] > right[25] > 0
    alone = Scene("board", scene.surfaces[1:], scene.azimuth_rad, scene.elevation_rad)
    single = render(alone, NOISELESS, np.random.default_rng(0))
    finite = np.isfinite(single.reference_depth)
    np.testing.assert_allclose(single.depth[-1][finite], single.reference_depth[finite], atol=1e-5)


def _hit_points(scene):
    scan = render(scene, NOISELESS, np.random.default_rng(0), coupling_gain=0.0)
    points = (scan.reference_depth[..., None] * grid_rays(scene.azimuth_rad, scene.elevation_rad)).reshape(-1, 3)
    return points[np.isfinite(points).all(1)].astype(np.float64)


@pytest.mark.unit
def test_corner__a_rolled_corner_has_a_horizontal_edge():
    # Each board of a 90-degree corner with its edge at z = 2 m, turned to run up and down from a horizontal
    # edge, holds the points with |y| = 2 - z.
    x, y, z = _hit_points(corner(90.0, 2.0, 0.6, height=24, width=32, roll_deg=90.0)).T
    np.testing.assert_allclose(np.abs(y), 2.0 - z, atol=1e-5)
    assert (y > 0.01).any() and (y < -0.01).any() and np.ptp(x) > 0.3


@pytest.mark.unit
def test_corner__yaw_turns_the_boards_about_the_edge_and_ends_them_at_their_length():
    half, yaw = np.deg2rad(50.0), np.deg2rad(15.0)
    scene = corner(100.0, 2.2, 0.7, height=24, width=48, board_m=0.25, yaw_deg=15.0, albedo_right=0.3)
    x, _, z = _hit_points(scene).T
    left, right = x < 0, x > 0
    # From the edge (0, 2.2) the left board runs at half + yaw from the view's axis, the right at half - yaw.
    np.testing.assert_allclose(-x[left], (2.2 - z[left]) * np.tan(half + yaw), atol=1e-5)
    np.testing.assert_allclose(x[right], (2.2 - z[right]) * np.tan(half - yaw), atol=1e-5)
    assert np.hypot(x, 2.2 - z).max() <= 0.25 + 1e-6, "no point beyond the boards' length"
    assert [surface.albedo for surface in scene.surfaces] == [0.7, 0.3]


@pytest.mark.unit
def test_room_corner_and_alcove__every_surface_is_seen():
    for scene in (room_corner(height=24, width=32), alcove(height=24, width=32)):
        _, which = first_hits(scene)
        assert set(which[which >= 0]) == set(range(len(scene.surfaces))), scene.name


@pytest.mark.unit
@pytest.mark.parametrize("pitch_deg", [20.0, 27.0])
def test_pitched_scenes__the_floor_lies_one_metre_below_the_sensor(pitch_deg):
    # Back in the world's frame (the rotation undone) every point the sensor sees on the floor has y = -1 m.
    for scene in (box_on_floor(pitch_deg=pitch_deg, height=24, width=32),
                  floor_meets_wall(pitch_deg=pitch_deg, height=24, width=32)):
        t, which = first_hits(scene)
        rays = grid_rays(scene.azimuth_rad, scene.elevation_rad).reshape(-1, 3)
        world = (t[which == 0, None] * rays[which == 0]) @ pitch_rotation(pitch_deg)
        np.testing.assert_allclose(world[:, 1], -1.0, atol=1e-9)
        assert (which == 0).sum() > 50 and (which == 1).sum() > 50, scene.name


@pytest.mark.unit
def test_box_on_floor__its_sides_and_back_are_hidden_but_light_the_floor():
    scene = box_on_floor(height=24, width=32)
    _, which = first_hits(scene)
    hidden = [2, 4, 5]  # back, left and right side
    assert not np.isin(which, hidden).any(), "the sensor sees neither the sides nor the back"
    # At the calibrated footprint (A_fp 0.041 m^2) the hidden faces add over 1 % to some floor pixel's light.
    gain = 0.041 / (np.pi * DEFAULT_FOOTPRINT_RADIUS_M**2)
    floor = which == 0
    hidden_only = Scene("hidden", (scene.surfaces[0], *(scene.surfaces[k] for k in hidden)), scene.azimuth_rad,
                        scene.elevation_rad)
    lit, _ = light_transport(hidden_only, Config(), DEFAULT_FOOTPRINT_RADIUS_M, 0.04, gain)
    alone, _ = light_transport(Scene("floor", scene.surfaces[:1], scene.azimuth_rad, scene.elevation_rad),
                               Config(), DEFAULT_FOOTPRINT_RADIUS_M, 0.04, gain)
    added = np.abs(lit[floor, -1] - alone[floor, -1]) / np.abs(alone[floor, -1])
    assert added.max() > 0.01


@pytest.mark.unit
def test_box_on_floor__its_top_sends_the_floor_no_light():
    # The top faces up like the floor: no light leaves the box's inside through it.
    scene = box_on_floor(height=24, width=32)
    truth: dict[str, np.ndarray] = {}
    light_transport(Scene("top", (scene.surfaces[0], scene.surfaces[3]), scene.azimuth_rad, scene.elevation_rad),
                    Config(), DEFAULT_FOOTPRINT_RADIUS_M, 0.04, 10.0, coupling_out=truth)
    _, which = first_hits(scene)
    assert (which == 0).sum() > 50
    assert not truth["coupling"][which == 0].any()


@pytest.mark.unit
def test_light_transport__a_solid_face_lights_only_what_lies_in_front_of_it():
    """A one-sided patch facing away from a board sends it nothing; turned round, or two-sided, the same patch
    lights it."""
    board = Rectangle((0.0, 0.0, 2.0), (0.5, 0.0, 0.0), (0.0, 0.5, 0.0), albedo=0.8)
    coupling = {}
    for name, half_v, two_sided in (("away", (0.0, 0.0, -0.01), False), ("towards", (0.0, 0.0, 0.01), False),
                                    ("board", (0.0, 0.0, -0.01), True)):
        patch = Rectangle((0.0, 0.3, 1.9), (0.01, 0.0, 0.0), half_v, albedo=0.9, two_sided=two_sided)
        truth: dict[str, np.ndarray] = {}
        light_transport(Scene(name, (board, patch), np.array([0.0]), np.array([0.0])), NOISELESS,
                        footprint_radius_m=0.012, patch_spacing_m=0.05, coupling_gain=90.0, coupling_out=truth)
        coupling[name] = truth["coupling"][0]
    # (0.01, 0, 0) x (0, 0, -0.01) points up, away from the board below the patch.
    assert coupling["away"] == 0.0
    assert coupling["towards"] > 0.0
    assert coupling["board"] == pytest.approx(coupling["towards"], rel=1e-12)


@pytest.mark.unit
def test_light_transport__one_patch_matches_the_two_path_closed_form():
    """A single small patch in front of a board: the depth bias is the closed form of eq 11 with its ratio."""
    board = Rectangle((0.0, 0.0, 2.0), (0.5, 0.0, 0.0), (0.0, 0.5, 0.0), albedo=0.8)
    patch = Rectangle((0.0, 0.3, 1.9), (0.01, 0.0, 0.0), (0.0, 0.0, 0.01), albedo=0.9)  # faces down/up
    scene = Scene("patch", (board, patch), np.array([0.0]), np.array([0.0]))
    truth: dict[str, np.ndarray] = {}
    phasor, dc = light_transport(scene, NOISELESS, footprint_radius_m=0.012, patch_spacing_m=0.05,
                                 coupling_gain=90.0, coupling_out=truth)
    a_point, b_point = np.array([0.0, 0.0, 2.0]), np.array([0.0, 0.3, 1.9])
    r = np.linalg.norm(b_point - a_point)
    cos_a = (b_point - a_point) @ [0, 0, -1] / r
    cos_b = abs((a_point - b_point) @ [0, 1, 0] / r)
    ratio = 0.8 * 0.9 * (cos_a * cos_b) ** 2 * 4e-4 * 90 * np.pi * 0.012**2 / (np.pi**2 * r**4)
    phase_bias = np.angle(phasor[0]) - 4 * np.pi * FREQS * 2.0 / C
    expected = two_path_phase_bias(ratio, 4 * np.pi * FREQS * r / C)
    np.testing.assert_allclose(np.angle(np.exp(1j * phase_bias)), expected, rtol=1e-9, atol=1e-12)
    gamma_d = 0.1794 * 0.8 / 4.0
    np.testing.assert_allclose(dc[0], gamma_d * (1 + ratio), rtol=1e-12)
    # the reported coupling is the white-surface kappa of the kernel, its distance the patch's
    np.testing.assert_allclose(truth["coupling"], ratio / (0.8 * 0.9), rtol=1e-12)
    # ... and its noise-free depth bias the phase's over 4 pi f / c
    np.testing.assert_allclose(truth["bias_m"][0], expected * C / (4 * np.pi * FREQS), rtol=1e-9)
    np.testing.assert_allclose(truth["d_ab_m"], r, rtol=1e-12)


@pytest.mark.unit
def test_first_hits__sky_pixels_have_no_surface():
    scene = Scene("sky", (Sphere((0.0, 0.0, 2.0), 0.1),), np.linspace(-0.5, 0.5, 5), np.array([0.0]))
    t, which = first_hits(scene)
    assert list(which) == [-1, -1, 0, -1, -1] and np.isinf(t[0])


@pytest.mark.unit
def test_scan_from_phasors__single_path_returns_its_depth_and_transient_agrees():
    depth_true = np.array([[1.5, 2.0], [2.2, 2.35]])
    gamma = 0.02
    phasor = gamma * np.exp(1j * 4 * np.pi * FREQS[:, None, None] * depth_true[None] / C)
    scan = scan_from_phasors("ext", phasor, NOISELESS, np.random.default_rng(0))
    np.testing.assert_allclose(scan.depth, np.broadcast_to(depth_true, scan.depth.shape), atol=1e-5)
    np.testing.assert_allclose(scan.amplitude, gamma, rtol=1e-5)
    bin_s = 1e-12
    histogram = np.zeros((20_000, 2, 2))
    bins = np.rint(2 * depth_true / C / bin_s).astype(int)
    for (y, x), b in np.ndenumerate(bins):
        histogram[b, y, x] = gamma
    transient = scan_from_transient("ext", histogram, bin_s, NOISELESS, np.random.default_rng(0))
    np.testing.assert_allclose(transient.depth, scan.depth, atol=2e-4)


@pytest.mark.unit
def test_render__reproducible_and_round_trips_through_a_store(tmp_path):
    scene = cornered_board(height=16, width=20)
    first = render(scene, Config(), np.random.default_rng(3))
    again = render(scene, Config(), np.random.default_rng(3))
    np.testing.assert_array_equal(first.depth, again.depth)
    back = read_scan(write_scan(first, tmp_path / "c.scan.zarr"))
    np.testing.assert_array_equal(back.depth, first.depth)
    np.testing.assert_array_equal(back.reference_mask, first.reference_mask)
    assert back.scene["coupling_gain"] == 90.0


@pytest.mark.integration
@pytest.mark.slow
def test_render__cornered_board_matches_the_papers_fig7_magnitude():
    scan = render(cornered_board(), Config(), np.random.default_rng(0))
    error = np.abs(scan.depth[-1] - scan.reference_depth)[scan.reference_mask]
    assert 3.5e-3 < error.mean() < 6.5e-3  # Fig. 7: 5.0 mm
    assert 0.015 < error.max() < 0.035  # Fig. 7: 2.4 cm
