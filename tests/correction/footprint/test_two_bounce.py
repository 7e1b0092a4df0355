from __future__ import annotations

import numpy as np
import pytest

from mpi_lidar.config import Config
from mpi_lidar.correction.footprint._partners import Patches
from mpi_lidar.correction.footprint._two_bounce import PatchedPlane, TwoBounce
from mpi_lidar.simulation.scenes import Rectangle, Scene
from mpi_lidar.simulation.scenes._multibounce import Occluders, multibounce_ratios, scene_patches, transfer_powers

SPACING_M = 0.05
ALBEDO = (0.7, 0.5, 0.3)


def _cube_corner() -> Scene:
    """Two walls (z = 0, x = 0) and a floor (y = 0), 0.6 m squares meeting at the origin, sending light into x, y,
    z > 0; each its own albedo."""
    x, y, z = np.eye(3) * 0.3

    def face(u: np.ndarray, v: np.ndarray, albedo: float) -> Rectangle:
        return Rectangle(tuple(u + v), tuple(u), tuple(v), albedo, two_sided=False)

    return Scene("cube corner", (face(x, y, ALBEDO[0]), face(y, z, ALBEDO[1]), face(z, x, ALBEDO[2])),
                 np.zeros(1), np.zeros(1))


@pytest.mark.unit
def test_two_bounce__matches_the_renderers_patch_exchange_on_a_cube_corner():
    """(F16) on the renderer's own uniform patches reproduces its two-bounce term (out T back / cos_i) at points
    of the floor, at every frequency, for any albedos."""
    scene = _cube_corner()
    config = Config()
    c = config.sensor.speed_of_light_m_per_s
    wavenumbers = 2 * np.pi * np.asarray(config.frequencies_hz) / c
    patches = scene_patches(scene, SPACING_M, None)
    transfer = transfer_powers(patches, Occluders(scene), wavenumbers, bounces=2)  # T alone: two patches
    points = np.array([[0.1, 0.0, 0.1], [0.3, 0.0, 0.1], [0.45, 0.0, 0.4], [0.2, 0.0, 0.25]])
    normals = np.tile([0.0, 1.0, 0.0], (points.shape[0], 1))
    cos_i = np.array([1.0, 0.8, 0.5, 0.3])
    area_m2 = 0.05
    expected = multibounce_ratios(scene, points, normals, np.full(points.shape[0], 2), cos_i, area_m2, patches,
                                  patches, transfer, Occluders(scene), wavenumbers).higher

    planes = [PatchedPlane(patches.normals[patches.surface == k][0],
                           Patches(patches.centres[patches.surface == k], patches.areas[patches.surface == k]))
              for k in range(3)]
    unit = TwoBounce(planes, config.frequencies_hz, c).at_points(points, planes[2].normal, cos_i, own=2)
    albedo = np.asarray(ALBEDO)
    found = area_m2 * albedo[2] * np.einsum("p,q,npqf->nf", albedo, albedo, unit)
    assert np.abs(expected).min() > 1e-4  # a real test: the two bounces are there
    np.testing.assert_allclose(found, expected, rtol=2e-4)  # the renderer sums in single precision
    assert np.all(unit[:, 2] == 0) and np.all(unit[:, :, 2] == 0)  # nothing through the floor's own plane


@pytest.mark.unit
def test_two_bounce__only_the_pairs_asked_for_and_none_of_two_planes():
    scene = _cube_corner()
    patches = scene_patches(scene, SPACING_M, None)
    planes = [PatchedPlane(patches.normals[patches.surface == k][0],
                           Patches(patches.centres[patches.surface == k], patches.areas[patches.surface == k]))
              for k in range(3)]
    points = np.array([[0.2, 0.0, 0.2]])
    two_bounce = TwoBounce(planes, (12.5e6,), 299_792_458.0)
    every = two_bounce.at_points(points, planes[2].normal, np.ones(1), own=2)
    one = two_bounce.at_points(points, planes[2].normal, np.ones(1), own=2, pairs=[(0, 1)])
    assert one[0, 0, 1, 0] == every[0, 0, 1, 0] != 0 and one[0, 1, 0, 0] == 0
    # The wall's and floor's corner alone: light from the wall to the floor comes back to the floor's plane.
    two_planes = TwoBounce([planes[0], planes[2]], (12.5e6,), 299_792_458.0)
    assert np.abs(two_planes.at_points(points, planes[2].normal, np.ones(1), own=1)).max() == 0.0


@pytest.mark.unit
def test_three_bounces__match_the_renderers_three_patch_paths_on_a_cube_corner():
    """(F17) on the renderer's own uniform patches reproduces its three-patch term (out T T back / cos_i, the
    difference of its three- and two-bounce renders) at points of the floor, for any albedos; the floor's own plane
    carries light in the middle of a path, never at its ends."""
    scene = _cube_corner()
    config = Config()
    c = config.sensor.speed_of_light_m_per_s
    wavenumbers = 2 * np.pi * np.asarray(config.frequencies_hz) / c
    patches = scene_patches(scene, SPACING_M, None)
    points = np.array([[0.1, 0.0, 0.1], [0.3, 0.0, 0.1], [0.45, 0.0, 0.4], [0.2, 0.0, 0.25]])
    normals = np.tile([0.0, 1.0, 0.0], (points.shape[0], 1))
    cos_i = np.array([1.0, 0.8, 0.5, 0.3])
    area_m2 = 0.05
    higher = [multibounce_ratios(scene, points, normals, np.full(points.shape[0], 2), cos_i, area_m2, patches,
                                 patches, transfer_powers(patches, Occluders(scene), wavenumbers, bounces),
                                 Occluders(scene), wavenumbers).higher for bounces in (2, 3)]
    expected = higher[1] - higher[0]

    planes = [PatchedPlane(patches.normals[patches.surface == k][0],
                           Patches(patches.centres[patches.surface == k], patches.areas[patches.surface == k]))
              for k in range(3)]
    two_bounce = TwoBounce(planes, config.frequencies_hz, c)
    two, three = two_bounce.bounces_at_points(points, planes[2].normal, cos_i, own=2)
    albedo = np.asarray(ALBEDO)
    found = area_m2 * albedo[2] * np.einsum("t,ntf->nf", albedo[two_bounce.triples].prod(1), three)
    assert np.all(np.abs(expected) > 0.2 * np.abs(higher[0]))  # a real test: a fifth of the two bounces' light or more
    np.testing.assert_allclose(found, expected, rtol=1e-3)  # the renderer sums in single precision
    through_floor = two_bounce.triples[:, 1] == 2
    assert np.abs(three[:, through_floor]).min() > 0  # A -> wall -> floor -> wall -> A
    assert np.all(three[:, (two_bounce.triples[:, 0] == 2) | (two_bounce.triples[:, 2] == 2)] == 0)
    np.testing.assert_array_equal(two, two_bounce.at_points(points, planes[2].normal, cos_i, own=2))
