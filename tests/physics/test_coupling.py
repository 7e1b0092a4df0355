"""The A -> B -> A coupling kernel against closed forms."""

from __future__ import annotations

import numpy as np
import pytest

from mpi_lidar.physics.coupling import (
    DEFAULT_COUPLING_GAIN,
    DEFAULT_FOOTPRINT_AREA_M2,
    DEFAULT_FOOTPRINT_RADIUS_M,
    footprint_area,
    footprint_coupling,
    pair_geometry,
)

pytestmark = pytest.mark.unit


def test_default_footprint__is_90_pi_12_mm_squared():
    assert DEFAULT_FOOTPRINT_RADIUS_M == 0.012 and DEFAULT_COUPLING_GAIN == 90.0
    assert DEFAULT_FOOTPRINT_AREA_M2 == footprint_area(0.012, 90.0) == 90.0 * np.pi * 0.012**2
    assert footprint_area(0.004, 1.0) == pytest.approx(np.pi * 16e-6, rel=1e-15)


def test_pair_geometry__facing_and_tilted_patches():
    a = np.array([0.0, 0.0, 0.0])
    up = np.array([0.0, 0.0, 1.0])
    r, cos_a, cos_b = pair_geometry(a, up, [0.0, 0.0, 0.5], -up)  # two patches face to face, 0.5 m apart
    assert (r, cos_a, cos_b) == (0.5, 1.0, 1.0)
    tilt = np.deg2rad(30)
    b_normal = [np.sin(tilt), 0.0, -np.cos(tilt)]
    r, cos_a, cos_b = pair_geometry(a, up, [0.0, 0.0, 2.0], b_normal)
    assert r == 2.0 and cos_a == 1.0 and cos_b == pytest.approx(np.cos(tilt), rel=1e-15)
    # B behind A, and A behind B: negative cosines
    _, cos_a, cos_b = pair_geometry(a, up, [0.0, 0.0, -1.0], up)
    assert cos_a == -1.0 and cos_b == 1.0
    # broadcasting: (n, 1, 3) against (1, m, 3)
    points = np.zeros((4, 1, 3))
    centres = np.column_stack([np.zeros(3), np.zeros(3), [1.0, 2.0, 4.0]])[None]
    r, cos_a, cos_b = pair_geometry(points, np.broadcast_to(up, (4, 1, 3)), centres, -up)
    assert r.shape == (4, 3)
    np.testing.assert_array_equal(r, np.broadcast_to([1.0, 2.0, 4.0], (4, 3)))


def test_footprint_coupling__two_small_facing_patches_closed_form():
    """Face to face at distance r, beam at normal incidence: kappa = dA_B A_fp / (pi^2 r^4)."""
    area_b, a_fp = 1e-4, DEFAULT_FOOTPRINT_AREA_M2
    for r in (0.05, 0.1, 0.3):
        got = footprint_coupling(1.0, 1.0, area_b, r, 1.0, a_fp)
        assert got == pytest.approx(area_b * a_fp / (np.pi**2 * r**4), rel=1e-15)
    # inverse fourth power of the distance, linear in both areas, 1 / cos_i, (cos_A cos_B)^2
    base = footprint_coupling(1.0, 1.0, area_b, 0.1, 1.0, a_fp)
    assert footprint_coupling(1.0, 1.0, area_b, 0.2, 1.0, a_fp) == pytest.approx(base / 16, rel=1e-14)
    assert footprint_coupling(1.0, 1.0, 2 * area_b, 0.1, 1.0, 3 * a_fp) == pytest.approx(6 * base, rel=1e-14)
    assert footprint_coupling(1.0, 1.0, area_b, 0.1, 0.5, a_fp) == pytest.approx(2 * base, rel=1e-14)
    assert footprint_coupling(0.5, 0.8, area_b, 0.1, 1.0, a_fp) == pytest.approx(0.16 * base, rel=1e-14)
    # the reflectance a b scales it to Gamma_M,B / Gamma_D
    assert footprint_coupling(1.0, 1.0, area_b, 0.1, 1.0, a_fp, reflectance=0.8 * 0.45) == pytest.approx(
        0.36 * base, rel=1e-14)


def test_footprint_coupling__integrates_to_the_half_plane_closed_form():
    """A point at distance a from the edge of a perpendicular half-plane: the integral of
    (cos_A cos_B)^2 / (pi^2 r^4) over the half-plane is 1 / (24 pi a^2)."""
    a = 0.1
    step = a / 20
    u = (np.arange(int(1 / step)) + 0.5) * step  # distance from the edge on the partner plane, to 1 m
    v = (np.arange(-int(1 / step), int(1 / step)) + 0.5) * step  # along the edge
    uu, vv = np.meshgrid(u, v, indexing="ij")
    # A at (a, 0, 0) on the plane z = 0 (normal +z); the partner is the half-plane x = 0, z > 0 (normal +x)
    centres = np.stack([np.zeros_like(uu), vv, uu], axis=-1)
    r, cos_a, cos_b = pair_geometry([a, 0.0, 0.0], [0.0, 0.0, 1.0], centres, [1.0, 0.0, 0.0])
    total = footprint_coupling(cos_a, cos_b, step**2, r, 1.0, 1.0).sum()
    assert total == pytest.approx(1 / (24 * np.pi * a**2), rel=1e-3)
