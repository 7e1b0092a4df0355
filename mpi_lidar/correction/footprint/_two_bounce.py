"""Light among the partner planes: two bounces A -> B -> C -> A (B and C on two different planes) and three,
A -> B -> C -> D -> A.

A pixel of a room corner faces two or three surfaces, and light goes from one of them to another before it
returns. With patches B (area dA_B) and C (area dA_C) of two partner planes and the point-to-patch factor

    g_XY = cos_X cos_Y / (pi max(r_XY, s)^2)   (s the larger patch side of the pair),

A sends g_AB dA_B of its light to B, B sends g_BC dA_C of what it got to C, and C sends g_CA A_fp back into the
footprint; at unit footprint and white surfaces the two-bounce phasor of A (seen at incidence cos_i) is

(F16)  S2_f = (1 / cos_i) sum_B sum_C g_AB dA_B g_BC dA_C g_CA e^{j 2 pi f (r_AB + r_BC + r_CA) / c},

summed per ordered pair of planes (P, Q) so that any albedos weigh it: the multipath ratio adds
A_fp rho_A sum_PQ rho_P rho_Q S2_PQ to the single bounces' (F5). It is the multi-bounce renderer's
``out T back / cos_i`` of two patches, with its caps: a point's and a patch's outgoing shares (sum g dA) are
held at most 1. The third bounce is the renderer's ``out T T back / cos_i``,

(F17)  S3_f = (1 / cos_i) sum_BCD g_AB dA_B g_BC dA_C g_CD dA_D g_DA e^{j 2 pi f (r_AB + r_BC + r_CD + r_DA) / c},

per ordered triple of planes (P, Q, R), weighed by rho_P rho_Q rho_R; C may lie on A's own plane (light crosses
it elsewhere), B and D may not. In a room it adds 60-70 % to the two bounces' light, over paths longer still: a
third of the rooms' 31.25 MHz bias. The planes' coarse patches (:attr:`PlanePartners.coarse_patches`) serve: the
light of several bounces changes slowly across a surface, as 1 / r^2 per leg and not as the single bounce's 1 / r^4.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from mpi_lidar.correction.footprint._partners import Patches, PlanePartners, on_plane
from mpi_lidar.correction.footprint._plane_coupling import dot3
from mpi_lidar.physics.coupling import pair_geometry


@dataclass(frozen=True)
class PatchedPlane:
    """A plane's unit normal (3,) (towards the room) and its patches."""

    normal: NDArray[np.float64]
    patches: Patches

    @property
    def sides_m(self) -> NDArray[np.float64]:
        return np.sqrt(self.patches.areas_m2)


class TwoBounce:
    """The two-bounce phasors (F16) of points on one plane from every ordered pair of other planes, and the
    three-bounce phasors (F17) from every ordered triple.

    Parameters
    ----------
    planes : list[PatchedPlane]
        Every plane of the scene (the points' own among them): the patch-to-patch transfer and its caps are
        worked out once over all of them.
    frequencies_hz : tuple[float, ...]
        Modulation frequencies. [Hz]
    speed_of_light_m_per_s : float
        c. [m/s]
    """

    def __init__(self, planes: list[PatchedPlane], frequencies_hz: tuple[float, ...], speed_of_light_m_per_s: float):
        self.planes = planes
        self.wavenumbers = 2 * np.pi * np.asarray(frequencies_hz, dtype=np.float64) / speed_of_light_m_per_s
        self.transfer = _transfers(planes)
        self._phased_transfers: dict[tuple[int, int, int], NDArray[np.complex128]] = {}
        # The ordered triples (B's plane, C's plane, D's plane) of three bounces whose two legs between planes face.
        self.triples = np.array([(p, q, s) for p, q in sorted(self.transfer) for s in range(len(planes))
                                 if (q, s) in self.transfer], dtype=np.intp).reshape(-1, 3)

    def at_points(self, points: NDArray, normal_a: NDArray, cos_i: NDArray, own: int | None = None,
                  pairs: list[tuple[int, int]] | None = None) -> NDArray[np.complex128]:
        """S2_f (n, P, P, F) of points (n, 3) [m] on a plane of unit normal ``normal_a`` (3,), plane ``own`` of
        ``planes`` where it is one of them, seen at incidence cosines ``cos_i`` (n,), per ordered pair (B's plane,
        C's plane); zero on the diagonal, through the own plane and for the pairs not in ``pairs`` (None: every
        pair)."""
        return self.bounces_at_points(points, normal_a, cos_i, own, pairs, three=False)[0]

    def bounces_at_points(self, points: NDArray, normal_a: NDArray, cos_i: NDArray, own: int | None = None,
                          pairs: list[tuple[int, int]] | None = None, three: bool = True
                          ) -> tuple[NDArray[np.complex128], NDArray[np.complex128]]:
        """:meth:`at_points`, and where ``three`` the three-bounce S3_f (n, T, F) (F17) per triple of
        :attr:`triples` (zero where B's or D's plane is the own one; C's may be: light crosses A's own surface
        elsewhere); (n, 0, F) where not ``three``."""
        count, n = len(self.planes), points.shape[0]
        found = np.zeros((n, count, count, self.wavenumbers.size), dtype=np.complex128)
        triples = self.triples if three else np.zeros((0, 3), dtype=np.intp)
        found_three = np.zeros((n, triples.shape[0], self.wavenumbers.size), dtype=np.complex128)
        if n == 0:
            return found, found_three
        legs = [_point_factors(points, normal_a, plane) if k != own else None for k, plane in enumerate(self.planes)]
        # A sends on at most all its light.
        share = sum(((leg[0] * plane.patches.areas_m2).sum(1) for leg, plane in zip(legs, self.planes, strict=True)
                     if leg is not None), np.zeros(n))
        out_scale = 1.0 / np.maximum(share, 1.0)
        wanted = pairs if pairs is not None else [(p, q) for p in range(count) for q in range(count)]
        # Light reaching C's plane q from A through B's plane p: the first two legs of both terms.
        firsts = sorted({(p, q) for p, q in wanted if q != own} | {(int(p), int(q)) for p, q, _ in triples})
        firsts = [(p, q) for p, q in firsts if p != q and legs[p] is not None and (p, q) in self.transfer]
        for f, k in enumerate(self.wavenumbers):
            through = {}
            for p, q in firsts:
                leg = legs[p]
                assert leg is not None  # the own plane's is None, and never among the firsts
                g_ab, r_ab = leg
                out = g_ab * self.planes[p].patches.areas_m2 * out_scale[:, None]
                through[(p, q)] = (out * np.exp(1j * k * r_ab)) @ self._phased(p, q, f)
            back = [None if leg is None else leg[0] * np.exp(1j * k * leg[1]) for leg in legs]
            for p, q in wanted:
                if (p, q) in through and back[q] is not None:
                    found[:, p, q, f] = (through[(p, q)] * back[q]).sum(1)
            # The light back into A from D's plane s, carried to C's plane q: C -> D -> A, per patch of C.
            returning: dict[tuple[int, int], NDArray] = {}
            for t, (p, q, s) in enumerate(triples):
                if (p, q) not in through or back[s] is None:
                    continue
                if (q, s) not in returning:
                    returning[(q, s)] = back[s] @ self._phased(q, s, f).T
                found_three[:, t, f] = (through[(p, q)] * returning[(q, s)]).sum(1)
        scale = 1.0 / np.maximum(cos_i, 1e-3)
        return found * scale[:, None, None, None], found_three * scale[:, None, None]

    def _phased(self, p: int, q: int, f: int) -> NDArray[np.complex128]:
        """The transfer from plane p's patches to plane q's with the phase of its legs at frequency index f (m_p,
        m_q), worked out once: every point of every plane the light is wanted at takes the same."""
        key = (p, q, f)
        if key not in self._phased_transfers:
            transfer, r = self.transfer[(p, q)]
            self._phased_transfers[key] = transfer * np.exp(1j * self.wavenumbers[f] * r)
        return self._phased_transfers[key]


def _point_factors(points: NDArray, normal_a: NDArray, plane: PatchedPlane) -> tuple[NDArray, NDArray]:
    """g_AX (n, m) and r_AX (n, m) [m] of points (n, 3) with normal ``normal_a`` to a plane's patches."""
    r, cos_a, cos_b = pair_geometry(points[:, None, :], normal_a, plane.patches.centres[None], plane.normal)
    facing = (cos_a > 0) & (cos_b > 0)
    return np.where(facing, cos_a * cos_b / (np.pi * np.maximum(r, plane.sides_m[None]) ** 2), 0.0), r


def _transfers(planes: list[PatchedPlane]) -> dict[tuple[int, int], tuple[NDArray, NDArray]]:
    """Per ordered pair of planes that face each other: the transfer g_BC dA_C (m_p, m_q) of B's light to C, each
    patch's total over all the planes held at most 1, and r_BC (m_p, m_q) [m]."""
    found: dict[tuple[int, int], tuple[NDArray, NDArray]] = {}
    for p, source in enumerate(planes):
        rows: dict[int, tuple[NDArray, NDArray]] = {}
        for q, target in enumerate(planes):
            if q == p:
                continue
            r, cos_b, cos_c = pair_geometry(source.patches.centres[:, None, :], source.normal,
                                            target.patches.centres[None], target.normal)
            clamp = np.maximum(source.sides_m[:, None], target.sides_m[None])
            share = np.where((cos_b > 0) & (cos_c > 0),
                             cos_b * cos_c * target.patches.areas_m2[None] / (np.pi * np.maximum(r, clamp) ** 2), 0.0)
            if share.any():
                rows[q] = (share, r)
        total = sum((share.sum(1) for share, _ in rows.values()), np.zeros(source.patches.areas_m2.size))
        scale = 1.0 / np.maximum(total, 1.0)
        for q, (share, r) in rows.items():
            found[(p, q)] = (share * scale[:, None], r)
    return found


@dataclass(frozen=True)
class PlaneBounces:
    """The light among the partner planes at some points (n,), at unit footprint and white surfaces.

    Attributes
    ----------
    two : NDArray[np.complex128]
        S2_f (n, P, P, F) (F16) per ordered pair of planes.
    three : NDArray[np.complex128]
        S3_f (n, T, F) (F17) per ordered triple of ``triples``.
    triples : NDArray[np.intp]
        The triples (T, 3) of plane indices.
    """

    two: NDArray[np.complex128]
    three: NDArray[np.complex128]
    triples: NDArray[np.intp]

    def phasor(self, partner_albedo: NDArray) -> NDArray[np.complex128]:
        """sum_PQ rho_P rho_Q S2_PQ + sum_PQR rho_P rho_Q rho_R S3_PQR (n, F) for the planes' albedos (P,) [1]."""
        found = np.einsum("p,q,npqf->nf", partner_albedo, partner_albedo, self.two)
        if self.triples.size:
            weight = partner_albedo[self.triples].prod(1)
            found += np.einsum("t,ntf->nf", weight, self.three)
        return found


def partner_bounces(partners: PlanePartners, rays: NDArray, surface: NDArray, frequencies_hz: tuple[float, ...],
                       speed_of_light_m_per_s: float) -> PlaneBounces | None:
    """The light among the partner planes (:attr:`PlanePartners.partners`) of the points where the rays (n, 3) meet
    the planes of their surfaces ``surface`` (n,): two bounces (F16) and three (F17), at unit footprint and white
    surfaces (zero for a point on no plane or on a surface without a facing partner); None where the scan has fewer
    than three partner planes (a corner of two has no such path: it needs a third).

    Every pair of planes other than the point's own counts, not only those whose blocks face within the partner
    range: two bounces reach over a room (a floor and a ceiling 1.3 m apart send each other light), and the
    factors' cosines leave out what does not face."""
    order = partners.partners
    if len(order) < 3:
        return None
    column = {label: k for k, label in enumerate(order)}
    owners = [own for own, facing in partners.facing.items() if facing and np.any(surface == own)]
    if not owners:
        return None
    empty = Patches(np.zeros((0, 3)), np.zeros(0))
    two_bounce = TwoBounce([PatchedPlane(partners.planes[label].normal, partners.coarse_patches.get(label, empty))
                            for label in order], frequencies_hz, speed_of_light_m_per_s)
    shape = (rays.shape[0], len(frequencies_hz))
    found = PlaneBounces(np.zeros((shape[0], len(order), len(order), shape[1]), dtype=np.complex128),
                         np.zeros((shape[0], two_bounce.triples.shape[0], shape[1]), dtype=np.complex128),
                         two_bounce.triples)
    for own in owners:
        rows = np.flatnonzero(surface == own)
        plane = partners.planes[own]
        cos_i = -dot3(rays[rows], plane.normal)
        found.two[rows], found.three[rows] = two_bounce.bounces_at_points(on_plane(rays[rows], plane), plane.normal,
                                                                          cos_i, column.get(own))
    return found
