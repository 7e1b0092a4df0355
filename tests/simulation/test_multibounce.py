from __future__ import annotations

import numpy as np
import pytest

from mpi_lidar.config import Config
from mpi_lidar.simulation.scenes import (
    Rectangle,
    Scene,
    corner,
    first_hits,
    light_transport,
    render,
    room_with_box,
    turned_room_with_box,
)
from mpi_lidar.simulation.scenes._multibounce import (
    Occluders,
    graded_rectangle,
    multibounce_transport,
    scene_patches,
    transfer_powers,
)

NOISELESS = Config().replace(simulator={"noise_scale": 0, "whole_cycles": True, "round_photons": False})
RADIUS_M, GAIN = 0.012, 90.0


def _tri_corner(floor_albedo: float = 0.7, floor: bool = True) -> Scene:
    """Two walls and a floor 0.6 m on a side meeting 2 m ahead, one-sided, seen on a 10 x 12 grid."""
    y = np.array([0.0, 1.0, 0.0])
    corner_point = np.array([0.0, -0.3, 2.0])
    left, right = np.array([-1.0, 0.0, -1.0]) / np.sqrt(2), np.array([1.0, 0.0, -1.0]) / np.sqrt(2)

    def face(u: np.ndarray, v: np.ndarray, albedo: float) -> Rectangle:
        inward = -np.cross(u, v) if np.cross(u, v) @ (np.zeros(3) - corner_point) < 0 else np.cross(u, v)
        half_v = 0.3 * v if np.cross(u, v) @ inward > 0 else -0.3 * v
        return Rectangle(tuple(corner_point + 0.3 * u + 0.3 * v), tuple(0.3 * u), tuple(half_v), albedo,
                         two_sided=False)

    surfaces = [face(left, y, 0.7), face(right, y, 0.7)]
    if floor:
        surfaces.append(face(left, right, floor_albedo))
    return Scene("tri", tuple(surfaces), np.linspace(-0.12, 0.12, 12), np.linspace(0.05, -0.12, 10),
                 notes={"bounces": 3.0})


@pytest.mark.unit
def test_multibounce_transport__single_bounce_with_uniform_patches_is_the_single_bounce_transport():
    """Higher bounces off, uniform patches: a two-board corner (nothing occludes) renders as today's transport."""
    scene = corner(90.0, 2.0, 0.8, height=6, width=10)
    expected_truth: dict[str, np.ndarray] = {}
    expected = light_transport(scene, NOISELESS, RADIUS_M, 0.04, GAIN, expected_truth)
    truth: dict[str, np.ndarray] = {}
    found = multibounce_transport(scene, NOISELESS, RADIUS_M, 0.04, GAIN, truth, bounces=1, grading_m=None)
    np.testing.assert_allclose(found[0], expected[0], rtol=2e-6, atol=1e-12)  # in single precision
    np.testing.assert_allclose(found[1], expected[1], rtol=1e-6)
    for key in ("coupling", "rho_aba", "d_ab_m", "bias_m"):
        np.testing.assert_allclose(truth[key], expected_truth[key], rtol=2e-5, atol=1e-9, err_msg=key)


@pytest.mark.unit
def test_multibounce_transport__graded_patches_keep_the_single_bounce_within_ten_percent():
    scene = corner(90.0, 2.0, 0.8, height=6, width=10)
    expected_truth: dict[str, np.ndarray] = {}
    light_transport(scene, NOISELESS, RADIUS_M, 0.03, GAIN, expected_truth)
    truth: dict[str, np.ndarray] = {}
    multibounce_transport(scene, NOISELESS, RADIUS_M, 0.03, GAIN, truth, bounces=1)
    assert scene_patches(scene, 0.03).size < 0.6 * scene_patches(scene, 0.03, None).size
    error = np.abs(truth["rho_aba"] / expected_truth["rho_aba"] - 1)
    assert np.median(error) < 0.01 and error.max() < 0.1  # the most at the edge, where r is clamped


@pytest.mark.unit
def test_multibounce_transport__two_planes_have_no_three_bounce_paths():
    """A -> B -> C -> A needs C off both A's plane and B's: two planes have none (C -> A or B -> C is coplanar)."""
    scene = corner(90.0, 2.0, 0.8, height=4, width=8)
    truth: dict[str, np.ndarray] = {}
    multibounce_transport(scene, NOISELESS, RADIUS_M, 0.04, GAIN, truth, bounces=2)
    assert np.abs(truth["single_ratio"]).max() > 1e-3
    assert np.abs(truth["higher_ratio"]).max() == 0.0
    truth_4: dict[str, np.ndarray] = {}
    multibounce_transport(scene, NOISELESS, RADIUS_M, 0.04, GAIN, truth_4, bounces=3)  # A -> B -> A' -> B' -> A
    assert np.abs(truth_4["higher_ratio"]).max() > 0.0


@pytest.mark.unit
def test_multibounce_transport__a_black_third_face_adds_nothing():
    """With the floor's albedo 0 the walls render as without the floor: no single bounce from it, no higher
    bounce through it (those left go wall to wall, A -> B -> A' -> B' -> A), and it occludes nothing."""
    truth: dict[str, np.ndarray] = {}
    black = _tri_corner(floor_albedo=0.0)
    # Uniform patches: graded ones would be finer next to the floor, present or not.
    phasor, _ = multibounce_transport(black, NOISELESS, RADIUS_M, 0.03, GAIN, truth, grading_m=None)
    assert np.abs(truth["single_ratio"][:, 2]).max() == 0.0
    walls = _tri_corner(floor=False)
    walls_truth: dict[str, np.ndarray] = {}
    expected = multibounce_transport(walls, NOISELESS, RADIUS_M, 0.03, GAIN, walls_truth, grading_m=None)
    _, which = first_hits(black)
    # Where no cap binds: the black floor takes its share of the footprint's white coupling (kappa <= 1) and of
    # what a point sends on (at most all its light), as a black surface does.
    on_walls = ((which == 0) | (which == 1)) & (truth["coupling"] < 0.999)
    assert on_walls.sum() > 60
    # ... to single precision: the higher bounces are summed in it, over patch sets of other sizes here
    np.testing.assert_allclose(phasor[on_walls], expected[0][on_walls], rtol=1e-6)
    np.testing.assert_allclose(truth["higher_ratio"][on_walls], walls_truth["higher_ratio"][on_walls], rtol=1e-4)
    lit: dict[str, np.ndarray] = {}
    multibounce_transport(_tri_corner(), NOISELESS, RADIUS_M, 0.03, GAIN, lit, grading_m=None)
    gained = np.abs(lit["higher_ratio"][on_walls, 0]) / np.abs(truth["higher_ratio"][on_walls, 0])
    assert np.median(gained) > 1.5  # a lit floor carries the walls' light to each other


@pytest.mark.unit
def test_transfer_powers__a_cube_centre_patch_sends_all_its_light_and_a_quarter_across():
    """Form factors inside a closed cube: from the middle of a face all light reaches the five other faces, and
    0.2394 of it the opposite face (the closed form of a point facing a centred square at its own side's
    distance: 4 (1 / 2 pi) 2 (A / sqrt(1 + A^2)) atan(A / sqrt(1 + A^2)), A = 1/2)."""
    c = np.array([0.0, 0.0, 3.0])
    faces = []
    for n in np.vstack([np.eye(3), -np.eye(3)]) * 0.5:  # each face's centre lies at c - n, facing +n
        u, v = np.roll(n, 1), np.roll(n, 2)
        faces.append(Rectangle(tuple(c - n), tuple(u), tuple(v if np.cross(u, v) @ n > 0 else -v), 1.0,
                               two_sided=False))
    x = np.array([0.5, 0.0, 0.0])
    scene = Scene("cube", tuple(faces), np.array([0.0]), np.array([0.0]))
    patches = scene_patches(scene, 1.0 / 15, None)
    total = transfer_powers(patches, Occluders(scene), np.array([0.0]), 2)[0].real  # T at k = 0, albedo 1
    middle = int(np.argmin(np.linalg.norm(patches.centres - (c - x), axis=1)))
    a = 0.5 / np.sqrt(1.25)
    assert total[middle].sum() == pytest.approx(1.0, abs=0.03)
    assert total[middle, patches.surface == 3].sum() == pytest.approx(4 / np.pi * a * np.arctan(a), rel=0.02)
    # reciprocity, dA_j F_jk = dA_k F_kj, between the patches whose share the cap at 1 left alone
    free = total.sum(1) < 0.999
    assert free.mean() > 0.2
    flux = (patches.areas[:, None] * total)[np.ix_(free, free)]
    np.testing.assert_allclose(flux, flux.T, rtol=1e-5, atol=1e-12)


@pytest.mark.unit
def test_occluders_visible__a_board_blocks_the_segments_that_cross_it():
    board = Rectangle((0.0, 0.0, 1.0), (0.2, 0.0, 0.0), (0.0, 0.2, 0.0))
    occluders = Occluders(Scene("board", (board,), np.array([0.0]), np.array([0.0])))
    p = np.array([[0.0, 0.0, 0.0], [0.5, 0.0, 0.0], [0.0, 0.0, 0.5]])
    q = np.array([[0.0, 0.0, 2.0], [0.8, 0.0, 2.0], [0.0, 0.19, 1.0], [0.0, 0.0, 0.9]])
    expected = np.array([[False, True, True, True],  # through the board; past its edge (x >= 0.27 > 0.2); ...
                         [True, True, True, True],  # ... beside it; on the board's plane
                         [False, True, True, True]])
    np.testing.assert_array_equal(occluders.visible(p, q), expected)


@pytest.mark.unit
def test_graded_rectangle__fine_beside_another_surface_and_the_same_area():
    wall = Rectangle((0.0, 0.5, 2.0), (0.5, 0.0, 0.0), (0.0, 0.5, 0.0))
    floor_points = np.column_stack([np.linspace(-0.5, 0.5, 50), np.zeros(50), np.full(50, 1.9)])
    centres, _, areas = graded_rectangle(wall, 0.02, 0.05, floor_points)
    assert areas.sum() == pytest.approx(1.0, rel=1e-12)
    low, high = centres[:, 1] < 0.05, centres[:, 1] > 0.8
    assert np.sqrt(areas[low]).max() <= 0.02 * (1 + 0.15 / 0.05)
    assert np.sqrt(areas[high]).min() > 2 * np.sqrt(areas[low]).max()


@pytest.mark.unit
def test_room_with_box__every_face_in_view_and_most_multipath_at_the_tri_corner():
    scene = room_with_box(height=12, width=16)
    truth: dict[str, np.ndarray] = {}
    scan = render(scene, NOISELESS, np.random.default_rng(0), truth_out=truth)
    _, which = first_hits(scene)
    assert {0, 1, 2} <= set(which.tolist()) and which.min() >= 0
    points = scan.reference_depth[..., None] * scan.rays()
    near_corner = np.linalg.norm(points - np.asarray(scene.tri_corners[0]), axis=-1).ravel() < 0.15
    bias = truth["bias_m"][:, -1]
    assert near_corner.any() and (bias > 0).mean() > 0.95
    assert np.median(bias[near_corner]) > 2 * np.median(bias[~near_corner])
    assert (np.abs(truth["higher_ratio"][:, 0]) > 0).mean() > 0.9  # the light bounces among all the surfaces
    assert scan.scene["bounces"] == 3


@pytest.mark.unit
def test_render__a_room_renders_at_its_own_footprint():
    scene = room_with_box(height=6, width=8, bounces=1, footprint_m2=0.024)
    scan = render(scene, NOISELESS, np.random.default_rng(0))
    assert 90.0 * np.pi * scan.scene["footprint_radius_m"] ** 2 == pytest.approx(0.024, rel=1e-12)
    given = render(scene, NOISELESS, np.random.default_rng(0), footprint_radius_m=0.012)
    assert given.scene["footprint_radius_m"] == 0.012


@pytest.mark.unit
def test_turned_room_with_box__two_tri_corners_and_the_ceiling_in_view():
    scene = turned_room_with_box(height=12, width=16, bounces=2)
    assert len(scene.tri_corners) == 2 and len(scene.folds) == 9
    _, which = first_hits(scene)
    assert {0, 1, 2, 3} <= set(which.tolist())  # two walls, floor, ceiling
