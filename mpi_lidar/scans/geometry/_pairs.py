"""The pairs of block planes that face each other, and what the coupling kernel needs of each."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from mpi_lidar.physics.coupling import footprint_coupling, pair_geometry

# A pair of blocks faces only where each cosine towards the other exceeds this many of its sds under the noise:
# on a flat surface both exceed it by chance in (1 - Phi(k))^2 of the pairs, about 1e-6 at k = 3.
FACING_SIGMAS = 3.0
# Candidate pairs tested at once: the test's temporaries take a few hundred bytes a pair, and a large scan with
# much usable surface has millions of candidates.
PAIRS_PER_CHUNK = 1 << 20


@dataclass(frozen=True)
class FacingPairs:
    """Block pairs (A, B) that face each other, with what the coupling kernel needs of each (P,).

    ``a`` and ``b`` index the usable blocks (:attr:`FacingBlocks.index`); the cosines, B's area [m^2], the
    clamped distance [m] and A's incidence cosine are the arguments of
    :func:`mpi_lidar.physics.coupling.footprint_coupling`; ``distance_m`` is the unclamped centre distance.
    """

    a: NDArray[np.intp]
    b: NDArray[np.intp]
    cos_a: NDArray[np.float64]
    cos_b: NDArray[np.float64]
    area_b_m2: NDArray[np.float64]
    r_eff_m: NDArray[np.float64]
    cos_i: NDArray[np.float64]
    distance_m: NDArray[np.float64]

    def kappa(self, footprint_area_m2: float) -> NDArray[np.float64]:
        """kappa_B of every pair for the footprint A_fp [m^2] (white surfaces)."""
        return footprint_coupling(self.cos_a, self.cos_b, self.area_b_m2, self.r_eff_m, self.cos_i,
                                  footprint_area_m2)


def pairs_within(points: NDArray, radius_m: float) -> NDArray[np.intp]:
    """Index pairs (P, 2) of the points (n, 3) [m] at most ``radius_m`` [m] apart, i < j in each, in ascending
    (i, j) order: the pair sums that follow do not depend on the tree's order."""
    from scipy.spatial import cKDTree  # imported where used: the start-up does not pay for it

    found = cKDTree(points).query_pairs(radius_m, output_type="ndarray").astype(np.intp, copy=False)
    return found[np.lexsort((found[:, 1], found[:, 0]))]


@dataclass(frozen=True)
class PlaneSpread:
    """How far noise can move the two planes of block pairs (P,): the sd of each normal's direction [rad] and
    the two centres' sds along their normals combined in quadrature [m]
    (:func:`~mpi_lidar.scans.geometry.plane_uncertainty`)."""

    normal_a_rad: NDArray[np.float64]
    normal_b_rad: NDArray[np.float64]
    centres_m: NDArray[np.float64]

    def cosine_sds(self, dist: NDArray) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """The sd of cos_A and of cos_B (P,) of pairs ``dist`` [m] apart: a normal's turn, and the centres'
        offsets along it over the distance."""
        with np.errstate(divide="ignore", invalid="ignore"):
            offsets = self.centres_m / np.maximum(dist, 1e-12)
        return np.hypot(self.normal_a_rad, offsets), np.hypot(self.normal_b_rad, offsets)


def pair_coupling(centre_a: NDArray, normal_a: NDArray, cos_i: NDArray, area_a: NDArray, centre_b: NDArray,
                  normal_b: NDArray, area_b: NDArray, noise_m: NDArray, footprint_area_m2: float, min_cos: float,
                  spread: PlaneSpread | None = None) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """kappa_B of block B at block A for pairs of fitted planes (P,), and their distance (P,) [m].

    The kernel is :func:`mpi_lidar.physics.coupling.footprint_coupling`; here a pair faces when both cosines
    exceed ``min_cos``, each centre stands clear of the other's plane by more than three times ``noise_m``
    (the two fits' summed residual RMS) [m] and, where ``spread`` gives the planes' uncertainty, each cosine
    exceeds ``FACING_SIGMAS`` times its sd; r is clamped below by the larger block's side.
    Centres (P, 3) [m], unit normals (P, 3), incidence cosines at A (P,) and block areas (P,) [m^2].
    """
    dist, facing, r_eff, cos_a, cos_b = _pair_terms(centre_a, normal_a, area_a, centre_b, normal_b, area_b,
                                                    noise_m, min_cos, spread)
    return np.where(facing, footprint_coupling(cos_a, cos_b, area_b, r_eff, cos_i, footprint_area_m2), 0.0), dist


def _pair_terms(centre_a: NDArray, normal_a: NDArray, area_a: NDArray, centre_b: NDArray, normal_b: NDArray,
                area_b: NDArray, noise_m: NDArray, min_cos: float, spread: PlaneSpread | None
                ) -> tuple[NDArray, ...]:
    """Distance, facing mask, clamped distance and the two cosines of block pairs (P,) (:func:`pair_coupling`)."""
    dist, cos_a, cos_b = pair_geometry(centre_a, normal_a, centre_b, normal_b)
    # Each centre must stand clear of the other's plane by more than the fits' noise can explain.
    margin = 3.0 * noise_m
    facing = (cos_a > min_cos) & (cos_b > min_cos) & (cos_a * dist > margin) & (cos_b * dist > margin)
    if spread is not None:
        # Two noisy planes of one flat surface tilt towards each other as often as away: a pair faces only
        # where both turns are beyond what the noise gives them.
        sd_a, sd_b = spread.cosine_sds(dist)
        facing &= (cos_a > FACING_SIGMAS * sd_a) & (cos_b > FACING_SIGMAS * sd_b)
    r_eff = np.maximum(dist, np.sqrt(np.maximum(area_b, area_a)))
    return dist, facing, r_eff, cos_a, cos_b


def facing_pairs(i: NDArray, j: NDArray, centres: NDArray, normals: NDArray, cos_i: NDArray, area: NDArray,
                 noise_m: NDArray, min_cos: float, normal_sd_rad: NDArray | None = None,
                 centre_sd_m: NDArray | None = None) -> FacingPairs:
    """Both orders (i, j) and (j, i) of the unordered pairs of usable blocks (i, j) that face each other:
    first every facing (i, j), then every (j, i).

    Facing is symmetric (the distance, the margin, the planes' spread and the clamp are; the two cosines swap
    places), so the test runs once per unordered pair. ``normal_sd_rad`` and ``centre_sd_m`` are the blocks'
    plane uncertainties (:class:`PlaneSpread`), None: the residual margin alone.
    """
    chunks = (slice(k, k + PAIRS_PER_CHUNK) for k in range(0, max(i.size, 1), PAIRS_PER_CHUNK))  # one if none
    parts = [_facing_part(i[chunk], j[chunk], centres, normals, area, noise_m[chunk], min_cos, normal_sd_rad,
                          centre_sd_m) for chunk in chunks]
    ki, kj, dist, r_eff, cos_a, cos_b = (np.concatenate(column) for column in zip(*parts, strict=True))
    a, b = np.concatenate([ki, kj]), np.concatenate([kj, ki])
    return FacingPairs(a, b, np.concatenate([cos_a, cos_b]), np.concatenate([cos_b, cos_a]), area[b],
                       np.tile(r_eff, 2), cos_i[a], np.tile(dist, 2))


def _facing_part(i: NDArray, j: NDArray, centres: NDArray, normals: NDArray, area: NDArray, noise_m: NDArray,
                 min_cos: float, normal_sd_rad: NDArray | None, centre_sd_m: NDArray | None) -> tuple[NDArray, ...]:
    """The facing ones of some candidate pairs (i, j): their blocks, distance, clamped distance and cosines."""
    spread = None
    if normal_sd_rad is not None and centre_sd_m is not None:
        spread = PlaneSpread(normal_sd_rad[i], normal_sd_rad[j], np.hypot(centre_sd_m[i], centre_sd_m[j]))
    dist, facing, r_eff, cos_a, cos_b = _pair_terms(centres[i], normals[i], area[i], centres[j], normals[j],
                                                    area[j], noise_m, min_cos, spread)
    keep = np.flatnonzero(facing)
    return i[keep], j[keep], dist[keep], r_eff[keep], cos_a[keep], cos_b[keep]


