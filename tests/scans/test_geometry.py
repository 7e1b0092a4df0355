from __future__ import annotations

import functools

import numpy as np
import pytest

from mpi_lidar.config import Config, SensorConfig
from mpi_lidar.correction import INVALID_FLAGS, CorrectionOptions, analyse_geometry, validity_flags
from mpi_lidar.correction.footprint import PlaneModelInputs
from mpi_lidar.physics.coupling import DEFAULT_FOOTPRINT_AREA_M2
from mpi_lidar.physics.noise import NoiseModel
from mpi_lidar.scans.geometry import facing_blocks, fit_block_planes, multipath_potential, point_cloud, surface_normals
from mpi_lidar.scans.geometry._pairs import pair_coupling
from mpi_lidar.scans.scan import Scan, grid_rays
from mpi_lidar.simulation.scenes import (
    Rectangle,
    Scene,
    corner,
    cylinder_scene,
    first_hits,
    flat_wall,
    render,
    sphere_scene,
)
from mpi_lidar.simulation.scenes._transport import patch_coupling


def valid_depth(scan) -> np.ndarray:
    """The raw 31.25 MHz depth where correction's validity mask keeps the pixel (sky: no return), else NaN."""
    noise = NoiseModel.for_sensor(SensorConfig(), scan.frequencies_hz)
    flags = validity_flags(scan.raw_pixels(), CorrectionOptions(), noise)
    valid = ~np.isin(flags, [int(f) for f in INVALID_FLAGS]).reshape(scan.shape)
    return np.where(valid, scan.depth[-1], np.nan)


def exact_depth(scene: Scene) -> np.ndarray:
    d, _ = first_hits(scene)
    return np.where(np.isfinite(d), d, np.nan).reshape(scene.elevation_rad.size, scene.azimuth_rad.size)


def rays_of(scene: Scene) -> np.ndarray:
    return grid_rays(scene.azimuth_rad, scene.elevation_rad)


@pytest.mark.unit
@pytest.mark.parametrize("tilt", [0.0, 30.0, 60.0])
def test_multipath_potential__plane_has_none_exact_and_noisy(tilt):
    scene = flat_wall(tilt, height=48, width=64)
    exact = multipath_potential(exact_depth(scene), rays_of(scene))
    assert exact.coupling.max() == 0.0 and exact.bias_m.max() == 0.0 and np.isnan(exact.d_ab_m).all()
    for seed in range(3):
        noisy = render(scene, Config(), np.random.default_rng(seed))
        assert multipath_potential(valid_depth(noisy), noisy.rays()).bias_m.max() == 0.0


@pytest.mark.unit
@pytest.mark.parametrize("make", [sphere_scene, cylinder_scene])
def test_multipath_potential__convex_objects_and_open_sky_have_none(make):
    scene = make(height=48, width=64)
    depth = exact_depth(scene)
    assert np.isnan(depth).mean() > 0.2, "the object is surrounded by sky"
    assert multipath_potential(depth, rays_of(scene)).coupling.max() == 0.0
    noisy = render(scene, Config(), np.random.default_rng(4))
    assert multipath_potential(valid_depth(noisy), noisy.rays()).coupling.max() == 0.0


@pytest.mark.unit
def test_multipath_potential__sky_only_scan_is_zero_without_warnings():
    rays = grid_rays(np.linspace(-0.1, 0.1, 16), np.linspace(0.1, -0.1, 12))
    with np.errstate(all="raise"):
        potential = multipath_potential(np.full((12, 16), np.nan), rays)
    assert potential.coupling.shape == (12, 16) and potential.coupling.max() == 0.0


def big_corner(height: int = 96, width: int = 160) -> tuple[Scene, np.ndarray]:
    """A 90-degree corner of two 3 m boards, edge 2 m ahead, facing the scanner; and each pixel's true
    distance a from the edge line [m]. The scan sees +-0.8 m around the edge: the integral needs the
    partner board's surroundings, and the scan only knows what it sees."""
    edge = np.array([0.0, 0.0, 2.0])
    left, right = np.array([-1.0, 0.0, -1.0]) / 2**0.5, np.array([1.0, 0.0, -1.0]) / 2**0.5
    boards = tuple(Rectangle(tuple(edge + along * 1.5), tuple(along * 1.5), (0.0, 1.5, 0.0)) for along in (left, right))
    scene = Scene("big_corner", boards, np.linspace(-0.4, 0.4, width), np.linspace(0.4, -0.4, height))
    points = point_cloud(exact_depth(scene), rays_of(scene))
    return scene, np.hypot(points[..., 0] - edge[0], points[..., 2] - edge[2])


@pytest.mark.unit
def test_multipath_potential__corner_matches_the_half_plane_closed_form():
    """Coupling of a point at a from the edge of a perpendicular half-plane: A_fp / (24 pi a^2 cos_i)
    (the integral of (cos_A cos_B)^2 / (pi^2 r^4) over the half-plane is 1 / (24 pi a^2)); the
    coupling-weighted mean distance is 1.6 a."""
    scene, a = big_corner()
    rays = rays_of(scene)
    potential = multipath_potential(exact_depth(scene), rays, max_range_m=1.5)
    cos_i = np.abs(rays[..., 0] + rays[..., 2]) / 2**0.5  # both boards are 45 degrees off the view axis
    expected = DEFAULT_FOOTPRINT_AREA_M2 / (24 * np.pi * a**2 * cos_i)
    middle = slice(40, 56)
    where = (a[middle] > 0.06) & (a[middle] < 0.2)
    assert where.sum() > 100
    ratio = potential.coupling[middle][where] / expected[middle][where]
    assert 0.75 < np.median(ratio) < 1.25
    assert np.quantile(ratio, 0.9) < 1.6 and np.quantile(ratio, 0.1) > 0.5
    d_ab_ratio = potential.d_ab_m[middle][where] / (1.6 * a[middle][where])
    assert 0.7 < np.median(d_ab_ratio) < 1.2


@pytest.mark.integration
def test_multipath_potential__corner_grows_towards_the_edge_and_agrees_with_the_renderer():
    scene = corner(90.0, 2.0, 0.8, height=32, width=128)
    truth: dict[str, np.ndarray] = {}  # the render's own light transport
    scan = render(scene, Config(), np.random.default_rng(5), footprint_radius_m=0.012, patch_spacing_m=0.02,
                  coupling_gain=90.0, truth_out=truth)
    potential = multipath_potential(valid_depth(scan), scan.rays())
    row = potential.coupling[16]
    right = row[64:]
    assert (right > 0).all()
    assert right[4] > right[20] > right[40] > right[60] > 0
    true = truth["coupling"].reshape(32, 128)
    where = (true > 0.01) & (true < 0.9)
    ratio = potential.coupling[where] / true[where]
    assert 0.6 < np.median(ratio) < 1.3, "the render's coupling, estimated from its own noisy depth"


def equivalent_rho_aba_of(scan) -> np.ndarray:
    """The geometry gate's estimate of the equivalent rho_ABA of every pixel (H, W) at the default footprint."""
    options = CorrectionOptions(footprint_area_m2=DEFAULT_FOOTPRINT_AREA_M2)
    scene = analyse_geometry(scan, valid_depth(scan).ravel(), options, SensorConfig(), with_model_inputs=True)
    rho_aba, _ = scene.model_inputs.pixels(np.arange(scan.shape[0] * scan.shape[1]), valid_depth(scan).ravel())
    return rho_aba.reshape(scan.shape)


def board_medians(left: float, right: float) -> list[float]:
    """The estimated equivalent rho_ABA on each board of a 90-degree corner seen 15 degrees off its bisector
    (each board at its own incidence), median over the pixels with a true coupling of 0.01-0.9; each board's
    median estimate / true lies within 0.65-1.4."""
    scene = corner(90.0, 2.0, left, height=64, width=96, yaw_deg=15.0, albedo_right=right)
    truth: dict[str, np.ndarray] = {}
    scan = render(scene, Config(), np.random.default_rng(6), truth_out=truth)
    estimate = equivalent_rho_aba_of(scan)
    true, coupling = truth["rho_aba"].reshape(scan.shape), truth["coupling"].reshape(scan.shape)
    where = (coupling > 0.01) & (coupling < 0.9)
    medians = []
    for side in (slice(0, scan.shape[1] // 2), slice(scan.shape[1] // 2, None)):  # the two boards
        inside = where[:, side]
        assert inside.sum() > 100
        assert 0.65 < np.median(estimate[:, side][inside] / true[:, side][inside]) < 1.4
        medians.append(float(np.median(estimate[:, side][inside])))
    return medians


@pytest.mark.integration
def test_equivalent_rho_aba__follows_the_renderer_and_the_partner_albedo():
    """The renderer's ratio over the albedo a cos_i the amplitude shows, estimated from the noisy scan."""
    same = board_medians(0.8, 0.8)
    dark_right = board_medians(0.9, 0.25)
    # Each board's multipath comes from the other: a dark right board sends the left one less of it.
    assert (dark_right[0] / dark_right[1]) / (same[0] / same[1]) == pytest.approx(0.25 / 0.9, rel=0.25)


@functools.cache
def rendered_corner(angle_deg: float) -> tuple[Scan, dict[str, np.ndarray]]:
    """A corner 48 x 96 and the render's truth, rendered once for the tests that share it (read-only)."""
    truth: dict[str, np.ndarray] = {}
    scan = render(corner(angle_deg, 2.0, 0.8, height=48, width=96), Config(), np.random.default_rng(2),
                  truth_out=truth)
    for value in [*vars(scan).values(), *truth.values()]:
        if isinstance(value, np.ndarray):
            value.flags.writeable = False
    return scan, truth


@pytest.mark.unit
@pytest.mark.parametrize("angle_deg", [90.0, 120.0])
def test_plane_model_inputs__follow_the_renderer_from_the_edge_outwards(angle_deg):
    """Per pixel from the partner planes, the equivalent rho_ABA stays within 0.85-1.45x of the renderer's in
    every quantile of it, up to the edge itself (the blocks' estimate read 0.08x there on the 120-degree
    corner and 1.6x a few centimetres out on the right-angled one), and d_AB within 1.5 cm."""
    scan, truth = rendered_corner(angle_deg)
    depth = valid_depth(scan).ravel()
    options = CorrectionOptions(footprint_area_m2=DEFAULT_FOOTPRINT_AREA_M2)
    scene = analyse_geometry(scan, depth, options, SensorConfig(), with_model_inputs=True)
    rho_aba, d_ab = scene.model_inputs.pixels(np.arange(depth.size), depth)
    where = (truth["coupling"] > 0.005) & (truth["coupling"] < 0.9)
    true = truth["rho_aba"]
    edges = np.quantile(true[where], [0.25, 0.5, 0.75, 0.9])
    bins = np.searchsorted(edges, true, side="right")
    for index in range(len(edges) + 1):
        inside = where & (bins == index)
        assert 0.85 < np.median(rho_aba[inside] / true[inside]) < 1.45, index
        assert abs(np.nanmedian(d_ab[inside] - truth["d_ab_m"][inside])) < 0.015, index


@pytest.mark.unit
def test_plane_model_inputs__without_a_plane_give_the_blocks_estimate():
    """A pixel on no flat surface (here: every pixel, with no plane given) keeps the blocks' estimate."""
    scan, _ = rendered_corner(90.0)
    depth = valid_depth(scan).ravel()
    inputs = analyse_geometry(scan, depth, CorrectionOptions(footprint_area_m2=DEFAULT_FOOTPRINT_AREA_M2),
                              SensorConfig(), with_model_inputs=True).model_inputs
    pixels = np.arange(depth.size)
    blocks_only = PlaneModelInputs(inputs.fallback)
    for found, expected in zip(blocks_only.pixels(pixels, depth), inputs.fallback.pixels(pixels), strict=True):
        np.testing.assert_array_equal(found, expected)
    assert np.abs(inputs.pixels(pixels, depth)[0] - blocks_only.pixels(pixels, depth)[0]).max() > 0.01


@pytest.mark.unit
def test_equivalent_rho_aba__planes_have_none():
    scan = render(flat_wall(30.0, height=48, width=64), Config(), np.random.default_rng(1))
    assert equivalent_rho_aba_of(scan).max() == 0.0


@pytest.mark.unit
def test_coupling_to_pixels__follows_the_inverse_square_of_the_distance_from_an_edge():
    """Coupling falling as 1 / a^2 from an edge is interpolated exactly between block centres, where a linear
    interpolation overstates it; pixels among blocks without coupling get exactly 0."""
    scene = flat_wall(0.0, height=16, width=64)
    blocks = facing_blocks(exact_depth(scene), rays_of(scene))
    hb, wb = blocks.usable.shape
    b = blocks.block_pixels
    a_blocks = (np.arange(wb) + 0.5) * b  # block centres' distance from the left border [px]
    values = np.tile(1.0 / a_blocks**2, hb)
    pixels = np.arange(b // 2, (wb - 1) * b + b // 2)  # the first row, from the first to the last block centre
    found = blocks.coupling_to_pixels(values, blocks.pixel_coordinates(pixels))
    np.testing.assert_allclose(found, 1.0 / (pixels + 0.5) ** 2, rtol=1e-9)
    assert (blocks.to_pixels(values, blocks.pixel_coordinates(pixels)) >= found * (1 - 1e-12)).all()
    assert blocks.coupling_to_pixels(np.zeros(hb * wb), blocks.pixel_coordinates(pixels)).max() == 0.0


@pytest.mark.unit
def test_coupling__renderer_and_gate_evaluate_the_same_kernel():
    """The renderer's per-patch coupling and the gate's per-block coupling are one kernel
    (mpi_lidar.physics.coupling): for the same pairs of points, normals, areas and incidence they agree, and
    both equal the closed form (cos_A cos_B)^2 dA_B A_fp / (pi^2 r^4 cos_i) where no clamp binds."""
    rng = np.random.default_rng(0)
    n = 40
    a_points = rng.uniform(-0.2, 0.2, (n, 3)) + np.array([0.0, 0.0, 2.0])
    a_normals = np.tile([0.0, 0.0, -1.0], (n, 1))
    b_point = np.array([0.0, 0.35, 1.8])
    b_normal = np.array([0.0, -1.0, 0.0])  # a small patch above the points A, facing down
    b_area = 1e-4
    cos_i = rng.uniform(0.5, 1.0, n)
    footprint = DEFAULT_FOOTPRINT_AREA_M2
    patch = Rectangle(tuple(b_point), (0.005, 0.0, 0.0), (0.0, 0.0, 0.01), albedo=1.0)
    np.testing.assert_allclose(patch.patches(0.01)[1][0], b_normal)  # its one patch faces down
    rendered, r = patch_coupling(a_points, a_normals, cos_i, 1.0, patch, b_point[None], b_normal[None],
                                  np.array([b_area]), footprint, 1e-3)
    gated, dist = pair_coupling(a_points, a_normals, cos_i, np.full(n, 1e-6), np.tile(b_point, (n, 1)),
                                 np.tile(b_normal, (n, 1)), np.full(n, b_area), np.zeros(n), footprint, 0.0)
    np.testing.assert_allclose(rendered[:, 0], gated, rtol=1e-14)
    np.testing.assert_array_equal(r[:, 0], dist)
    offset = b_point - a_points
    distance = np.linalg.norm(offset, axis=1)
    cos_a = offset @ [0.0, 0.0, -1.0] / distance
    cos_b = -offset @ b_normal / distance
    expected = (cos_a * cos_b) ** 2 * b_area * 90 * np.pi * 0.012**2 / (np.pi**2 * distance**4 * cos_i)
    assert (cos_a > 0).all() and (cos_b > 0).all() and (expected > 0).all()
    np.testing.assert_allclose(gated, expected, rtol=1e-12)


@pytest.mark.unit
def test_fit_block_planes__ignores_a_depth_edge_inside_the_block():
    rays = grid_rays(np.linspace(-0.05, 0.05, 8), np.linspace(0.05, -0.05, 8))
    depth = np.full((8, 8), 2.0) / rays[..., 2]  # the plane z = 2
    depth[:, :2] = 3.0  # a quarter of the block sees a wall 1 m further back
    centres, normals, keep, usable, rms = fit_block_planes(point_cloud(depth, rays), 8)
    np.testing.assert_allclose(normals[0, 0], [0.0, 0.0, -1.0], atol=1e-9)
    assert usable[0, 0] and keep[0, 0].sum() == 48 and rms[0, 0] < 1e-9
    assert centres[0, 0, 2] == pytest.approx(2.0, abs=1e-12)


@pytest.mark.unit
def test_surface_normals__plane_gives_its_normal_towards_the_scanner():
    az, el = np.linspace(-0.3, 0.3, 20), np.linspace(-0.2, 0.2, 15)
    rays = grid_rays(az, el)
    normal = np.array([0.3, 0.0, -1.0]) / np.linalg.norm([0.3, 0.0, -1.0])
    depth = 2.0 / -(rays @ normal)  # plane n . p = -2
    normals = surface_normals(point_cloud(depth, rays))
    np.testing.assert_allclose(normals[2:-2, 2:-2], np.broadcast_to(normal, normals[2:-2, 2:-2].shape), atol=1e-9)


@pytest.mark.unit
def test_facing_blocks__pairs_tested_a_chunk_at_a_time_are_the_pairs_tested_at_once(monkeypatch):
    """The facing test runs a bounded number of candidate pairs at a time (memory on large scans); chunks of 7
    pairs, cutting through both orders of many pairs, give the same pairs in the same order."""
    from mpi_lidar.scans.geometry import _pairs

    scene = corner(90.0, 2.0, 0.8, 48, 64)
    whole = facing_blocks(exact_depth(scene), rays_of(scene))
    monkeypatch.setattr(_pairs, "PAIRS_PER_CHUNK", 7)
    chunked = facing_blocks(exact_depth(scene), rays_of(scene))
    assert whole.pairs.a.size > 100
    for name in ("a", "b", "cos_a", "cos_b", "area_b_m2", "r_eff_m", "cos_i", "distance_m"):
        np.testing.assert_array_equal(getattr(chunked.pairs, name), getattr(whole.pairs, name), err_msg=name)
