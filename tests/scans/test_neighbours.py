"""The numpy neighbour searches and interpolation against scipy's, the independent method: cKDTree's pairs and
nearest points, ndimage.map_coordinates at order 1 with mode "nearest"."""

from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays
from scipy.ndimage import map_coordinates
from scipy.spatial import cKDTree

from mpi_lidar.scans import neighbours
from mpi_lidar.scans.neighbours import NearestPoints, bilinear, pairs_within

DISTANCE_TOLERANCE = 1e-12


def ascending(pairs: np.ndarray) -> np.ndarray:
    """Pairs (P, 2) in ascending (i, j): the searches give them in orders of their own."""
    pairs = pairs.reshape(-1, 2)
    return pairs[np.lexsort((pairs[:, 1], pairs[:, 0]))]


def scipy_pairs(points: np.ndarray, radius: float) -> np.ndarray:
    """cKDTree's pairs (P, 2), i < j, in ascending (i, j)."""
    return ascending(cKDTree(points).query_pairs(radius, output_type="ndarray"))


def point_sets() -> dict[str, tuple[np.ndarray, float]]:
    """Named point sets (n, 3) [m] (one of them (n, 2)) and a radius [m] for each, degenerate ones among them."""
    rng = np.random.default_rng(7)
    spread = rng.uniform(-1, 1, (600, 3))
    repeated = np.concatenate([spread[:100], spread[:100], spread[50:150]])
    line = np.linspace(0, 1, 200)[:, None] * np.array([1.0, 2.0, -0.5])
    lattice = np.stack(np.meshgrid(*(np.arange(5.0),) * 3, indexing="ij"), axis=-1).reshape(-1, 3)
    clump = 1e-4 * rng.uniform(size=(80, 3)) + 3.0
    return {"spread": (spread, 0.2), "repeated": (repeated, 0.15), "line": (line, 0.02),
            "lattice one apart": (lattice, 1.0), "clump, all in one cell": (clump, 1.0),
            "clump and a far point": (np.concatenate([clump, [[1e6, 0, 0]]]), 1e-5),
            "huge radius": (spread[:60], 1e9), "infinite radius": (spread[:30], np.inf),
            "tiny radius and duplicates": (repeated, 1e-12), "zero radius": (repeated, 0.0),
            "one point": (spread[:1], 1.0), "two points": (spread[:2], 10.0), "none": (np.zeros((0, 3)), 1.0),
            "one place": (np.zeros((20, 3)), 0.0), "two dimensions": (spread[:, :2], 0.1)}


@pytest.mark.parametrize("name", list(point_sets()))
def test_pairs_within__same_pairs_as_ckdtree(name):
    points, radius = point_sets()[name]
    found = pairs_within(points, radius)
    assert found.dtype == np.intp and found.shape[1] == 2
    assert (found[:, 0] < found[:, 1]).all()
    np.testing.assert_array_equal(ascending(found), scipy_pairs(points, radius))


@settings(max_examples=60, deadline=None)
@given(arrays(np.int8, st.tuples(st.integers(0, 60), st.just(3)), elements=st.integers(-4, 4)),
       st.sampled_from([0.0, 0.5, 1.0, 1.5, 3.0, 20.0]))
def test_pairs_within__small_integer_points_with_ties(points, radius):
    """Integer coordinates: many duplicates and pairs exactly one radius apart."""
    points = points.astype(np.float64)
    np.testing.assert_array_equal(ascending(pairs_within(points, radius)), scipy_pairs(points, radius))


@pytest.mark.parametrize("name", ["spread", "repeated", "lattice one apart"])
def test_searches__chunks_of_a_few_candidates_change_nothing(name, monkeypatch):
    """Chunk boundaries fall inside cells and between a position's candidates."""
    points, radius = point_sets()[name]
    monkeypatch.setattr(neighbours, "CANDIDATES_PER_CHUNK", 50)
    monkeypatch.setattr(neighbours, "BRUTE_FORCE_PAIRS", 0)
    np.testing.assert_array_equal(ascending(pairs_within(points, radius)), scipy_pairs(points, radius))
    distance, _ = NearestPoints(points).nearest_other()
    expected = cKDTree(points).query(points, k=2)[0][:, 1]
    np.testing.assert_allclose(distance, expected, rtol=0, atol=DISTANCE_TOLERANCE)


@pytest.fixture(params=["compare all", "tree"])
def search(request, monkeypatch):
    """Both ways a nearest-point search goes: every position with every point, and down the tree of cells."""
    if request.param == "tree":
        monkeypatch.setattr(neighbours, "BRUTE_FORCE_PAIRS", 0)
    return request.param


def assert_same_nearest(distance: np.ndarray, index: np.ndarray, expected_distance: np.ndarray,
                        expected_index: np.ndarray, unique: np.ndarray) -> None:
    """Distances as scipy's; indices as scipy's where the nearest distance is unique."""
    np.testing.assert_allclose(distance, expected_distance, rtol=0, atol=DISTANCE_TOLERANCE)
    np.testing.assert_array_equal(index[unique], expected_index[unique])


@pytest.mark.parametrize("name", list(point_sets()))
def test_nearest__as_ckdtree_near_and_far(name, search):
    points, _ = point_sets()[name]
    rng = np.random.default_rng(3)
    scale = max(float(np.ptp(points, axis=0).max()) if points.size else 1.0, 1e-3)
    positions = np.concatenate([
        points[:50] + rng.normal(0, 0.01 * scale, (min(50, points.shape[0]), points.shape[1])),
        points[:20],  # on a point
        rng.normal(0, 10 * scale, (40, points.shape[1])),  # far outside
    ]) if points.size else rng.normal(size=(5, points.shape[1]))
    distance, index = NearestPoints(points).nearest(positions)
    if points.shape[0] == 0:
        assert np.isinf(distance).all() and (index == 0).all()
        return
    expected, expected_index = cKDTree(points).query(positions, k=2)  # inf and n for a missing second
    unique = expected[:, 0] < expected[:, 1]
    assert_same_nearest(distance, index, expected[:, 0], expected_index[:, 0], unique)


@pytest.mark.parametrize("name", list(point_sets()))
def test_nearest_other__second_neighbour_of_ckdtree(name, search):
    points, _ = point_sets()[name]
    distance, index = NearestPoints(points).nearest_other()
    n = points.shape[0]
    if n < 2:
        assert distance.shape == (n,) and np.isinf(distance).all() and (index == n).all()
        return
    expected, expected_index = cKDTree(points).query(points, k=min(3, n))
    np.testing.assert_allclose(distance, expected[:, 1], rtol=0, atol=DISTANCE_TOLERANCE)
    # The second neighbour is the nearest other point unless a duplicate stands in for the point itself.
    unique = (expected[:, 0] < expected[:, 1]) & (expected[:, 1] < expected[:, 2] if n > 2 else True)
    np.testing.assert_array_equal(index[unique], expected_index[unique, 1])
    assert (index != np.arange(n)).all()


@settings(max_examples=40, deadline=None)
@given(arrays(np.int8, st.tuples(st.integers(1, 40), st.just(3)), elements=st.integers(-3, 3)),
       arrays(np.int8, st.tuples(st.integers(1, 20), st.just(3)), elements=st.integers(-6, 6)),
       st.booleans())
def test_nearest__integer_points_ties_go_to_the_lowest_index(points, positions, tree):
    points, positions = points.astype(np.float64), positions.astype(np.float64)
    limit = 0 if tree else neighbours.BRUTE_FORCE_PAIRS
    original, neighbours.BRUTE_FORCE_PAIRS = neighbours.BRUTE_FORCE_PAIRS, limit
    try:
        distance, index = NearestPoints(points).nearest(positions)
    finally:
        neighbours.BRUTE_FORCE_PAIRS = original
    table = np.linalg.norm(positions[:, None, :] - points[None, :, :], axis=-1)
    np.testing.assert_allclose(distance, cKDTree(points).query(positions)[0], rtol=0, atol=DISTANCE_TOLERANCE)
    np.testing.assert_array_equal(index, np.argmin(table, axis=1))


def test_nearest__many_points_on_a_sphere_and_positions_off_it(search):
    """Unit ray directions, the footprint fit's use, with positions inside, on and outside the sphere."""
    rng = np.random.default_rng(11)
    rays = rng.normal(size=(3000, 3))
    rays /= np.linalg.norm(rays, axis=1, keepdims=True)
    rays[:, 2] = np.abs(rays[:, 2])
    positions = np.concatenate([rng.normal(size=(1500, 3)), rays[:200] * 1.0000001, 5 * rng.normal(size=(100, 3))])
    distance, index = NearestPoints(rays).nearest(positions)
    expected, expected_index = cKDTree(rays).query(positions, k=2)
    assert_same_nearest(distance, index, expected[:, 0], expected_index[:, 0], expected[:, 0] < expected[:, 1])
    other, _ = NearestPoints(rays).nearest_other()
    np.testing.assert_allclose(other, cKDTree(rays).query(rays, k=2)[0][:, 1], rtol=0, atol=DISTANCE_TOLERANCE)


def test_nearest__positions_of_an_empty_set_are_infinitely_far():
    distance, index = NearestPoints(np.zeros((0, 3))).nearest(np.ones((4, 3)))
    assert np.isinf(distance).all() and (index == 0).all()
    distance, index = NearestPoints(np.ones((3, 3))).nearest(np.zeros((0, 3)))
    assert distance.shape == (0,) and index.shape == (0,)


def grids() -> dict[str, np.ndarray]:
    rng = np.random.default_rng(5)
    with_nan = rng.normal(size=(6, 7))
    with_nan[2, 3] = np.nan
    return {"1x1": rng.normal(size=(1, 1)), "1x5": rng.normal(size=(1, 5)), "4x1": rng.normal(size=(4, 1)),
            "2x3": rng.normal(size=(2, 3)), "20x30": rng.normal(size=(20, 30)), "a NaN": with_nan,
            "blocks' couplings": 10.0 ** rng.uniform(-9, 0, size=(20, 20))}


@pytest.mark.parametrize("name", list(grids()))
def test_bilinear__map_coordinates_order_1_nearest_inside_and_outside_the_grid(name):
    values = grids()[name]
    h, w = values.shape
    rng = np.random.default_rng(9)
    rows = rng.uniform(-3, h + 2, 100_000)  # more than one chunk
    columns = rng.uniform(-3, w + 2, 100_000)
    rows[:2000] = np.round(rows[:2000])  # on grid lines, the edges and beyond
    columns[1000:3000] = np.round(columns[1000:3000])
    rows[3000:3100], columns[3100:3200] = -1e9, 1e9
    found = bilinear(values, rows, columns)
    expected = map_coordinates(values, (rows, columns), order=1, mode="nearest")
    np.testing.assert_allclose(found, expected, rtol=0, atol=DISTANCE_TOLERANCE)
    np.testing.assert_array_equal(found, expected)  # the same arithmetic: the same bits


def test_bilinear__pixel_centres_of_blocks_keep_the_grid_shape():
    values = np.random.default_rng(2).normal(size=(4, 5))
    b = 7
    rows, columns = np.meshgrid((np.arange(30) + 0.5) / b - 0.5, (np.arange(33) + 0.5) / b - 0.5, indexing="ij")
    found = bilinear(values, rows, columns)
    assert found.shape == (30, 33)
    np.testing.assert_array_equal(found, map_coordinates(values, (rows, columns), order=1, mode="nearest"))
    assert bilinear(values, np.zeros(0), np.zeros(0)).shape == (0,)


def test_correction_path__imports_neither_scipy_spatial_nor_ndimage():
    """Their imports cost a one-scan correction about 0.1 s: the geometry stage (facing blocks, the footprint fit,
    a geometric model's inputs) runs on this module instead, in a fresh interpreter."""
    code = """
import json, sys
import numpy as np
from mpi_lidar.config import Config, SensorConfig
from mpi_lidar.correction import CorrectionOptions, analyse_geometry
from mpi_lidar.simulation.scenes import SCENES, render
scan = render(SCENES["cornered_board"](height=48, width=64), Config(), np.random.default_rng(0), patch_spacing_m=0.05)
depth = np.asarray(scan.depth[-1], dtype=np.float64).ravel()
scene = analyse_geometry(scan, np.where(depth > 0, depth, np.nan), CorrectionOptions(), SensorConfig(),
                         with_model_inputs=True)
loaded = sorted(m for m in sys.modules if m in ("scipy.spatial", "scipy.ndimage"))
print(json.dumps([scene.blocks.pairs.a.size, loaded]))
"""
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    pairs, loaded = json.loads(done.stdout.strip().splitlines()[-1])
    assert pairs > 0, "the scan has facing blocks, so the searches ran"
    assert loaded == []
