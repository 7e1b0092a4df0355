"""The coupling model: the unit-footprint multipath phasor of blocks and pixels, for any albedos.

The renderer's two-path model gives every pixel A and frequency f the ratio of multipath to direct light

(F5)  ratio_f = A_fp S_f / max(A_fp K, 1),   S_f = rho_A sum_B rho_B kappa_B e^{j 4 pi f r_AB / c},
      K = sum_B kappa_B,

with kappa_B the partner's coupling at A_fp = 1 m^2 ((F4), or a block pair's), r_AB the distance A-B [m] and the
white coupling K capping it like the renderer (at A_fp K > 1 the multipath is scaled by 1 / (A_fp K)). The
measured depth and amplitude then carry

(F6)  bias_f = (c / 4 pi f) arg(1 + ratio_f) [m],   gain_f = |1 + ratio_f|.

:class:`PlaneCoupling` works out the scan's side once (the partner planes, their sums at the block centres, the
block pairs they do not describe), :class:`PixelCoupling` S_f and K of some pixels, :class:`BlockPhasors` the
sums of block pairs.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from mpi_lidar.config import SensorConfig
from mpi_lidar.correction.footprint._facing_pairs import BlockPairs
from mpi_lidar.correction.footprint._partners import PlanePartners
from mpi_lidar.correction.footprint._surfaces import SurfaceLabels
from mpi_lidar.correction.footprint._two_bounce import partner_bounces
from mpi_lidar.scans.geometry import FacingBlocks
from mpi_lidar.scans.scan import Scan


class BlockPhasors:
    """The multipath phasor S_f per block at unit footprint (F5) of some block pairs, for any albedos: the
    pairs' phases are worked out once.

    Parameters
    ----------
    blocks : FacingBlocks
        The scan's blocks.
    frequencies_hz : tuple[float, ...]
        Modulation frequencies. [Hz]
    speed_of_light_m_per_s : float
        c. [m/s]
    pairs : BlockPairs
        The pairs summed (A the receiving block).
    """

    def __init__(self, blocks: FacingBlocks, frequencies_hz: tuple[float, ...], speed_of_light_m_per_s: float,
                 pairs: BlockPairs):
        self.block_count = blocks.usable.size
        self.block_a, self.block_b, self.kappa = pairs.receiver, pairs.partner, pairs.kappa
        freqs = np.asarray(frequencies_hz, dtype=np.float64)
        phase = 4 * np.pi * pairs.distance_m[:, None] * freqs[None, :] / speed_of_light_m_per_s
        self.cos, self.sin = np.cos(phase), np.sin(phase)

    def __call__(self, albedo: NDArray) -> NDArray[np.complex128]:
        """S_f per block (Hb*Wb, F) for the albedos per block ``albedo`` (Hb*Wb,)."""
        weight = self.kappa * albedo[self.block_a] * albedo[self.block_b]
        phasor = np.zeros((self.block_count, self.cos.shape[1]), dtype=np.complex128)
        for k in range(self.cos.shape[1]):
            phasor[:, k] = (np.bincount(self.block_a, weight * self.cos[:, k], minlength=self.block_count)
                            + 1j * np.bincount(self.block_a, weight * self.sin[:, k], minlength=self.block_count))
        return phasor


@dataclass(frozen=True)
class PairGroup:
    """Block pairs the partner planes do not describe, summed per receiving block.

    Attributes
    ----------
    phasors : BlockPhasors
        Their S_f per block for any albedos.
    coupling_at_blocks : NDArray[np.float64]
        Their white coupling K per receiving block at A_fp = 1 m^2 (Hb*Wb,). [1]
    receivers_on_plane : bool
        Whether the receivers lie on a partner plane (curved partners) or on none.
    """

    phasors: BlockPhasors
    coupling_at_blocks: NDArray[np.float64]
    receivers_on_plane: bool


class PlaneCoupling:
    """A scan's side of :class:`PixelCoupling`: the partner planes (:class:`PlanePartners`), their unit-footprint
    sums at the block centres and the block pairs they do not describe, worked out once for any pixels.

    Parameters
    ----------
    scan, blocks : Scan, FacingBlocks
        The scan and its blocks.
    surfaces : SurfaceLabels
        Its surfaces (:func:`surface_labels`).
    sensor : SensorConfig
        The sensor (its speed of light).
    fitted_planes : dict[int, NDArray] | None
        Planes u . x = 1 (u [1/m]) by flat-surface label that replace those through the block centres.

    Read-only once made, so threads may share it.
    """

    def __init__(self, scan: Scan, blocks: FacingBlocks, surfaces: SurfaceLabels, sensor: SensorConfig,
                 fitted_planes: dict[int, NDArray] | None = None):
        labels = surfaces.flat
        self.scan, self.blocks = scan, blocks
        self.speed_of_light_m_per_s = sensor.speed_of_light_m_per_s
        self.partners = PlanePartners(scan, blocks, surfaces.components, labels, fitted_planes)
        self.grid: NDArray[np.intp] = labels.reshape(blocks.usable.shape)
        self.at_points = functools.partial(self.partners.at_points, frequencies_hz=scan.frequencies_hz,
                                           speed_of_light_m_per_s=sensor.speed_of_light_m_per_s)
        block_rows, block_columns = np.divmod(np.arange(labels.size), blocks.usable.shape[1])
        centre_range = np.linalg.norm(blocks.centres.reshape(-1, 3), axis=1)
        block_surface = self.partners.nearest_surface(self.partners.block_rays, centre_range, block_rows,
                                                      block_columns, self.grid)
        # Per block and partner plane: the unit-footprint sums (Hb*Wb, P, F) and (Hb*Wb,) of the planes.
        self.unit_plane_phasor_at_blocks, plane_kappa = self.at_points(self.partners.block_rays, block_surface)
        self.plane_coupling_at_blocks = plane_kappa.sum(1)
        # Per block: the light among the partner planes, two bounces (F16) and three (F17); None with fewer than
        # three partner planes (a corner of two has no such light).
        self.unit_bounces_at_blocks = partner_bounces(self.partners, self.partners.block_rays, block_surface,
                                                            scan.frequencies_hz, sensor.speed_of_light_m_per_s)
        # The block pairs of receivers on a plane with curved partners, and of receivers on no plane.
        self.pair_groups = [
            PairGroup(BlockPhasors(blocks, scan.frequencies_hz, sensor.speed_of_light_m_per_s, pairs),
                      np.bincount(pairs.receiver, pairs.kappa, minlength=blocks.usable.size).astype(np.float64),
                      on_plane)
            for pairs, on_plane in ((self.partners.curved, True), (self.partners.off_plane, False)) if pairs.size]

    @functools.cached_property
    def coupling_at_blocks(self) -> NDArray[np.float64]:
        """White coupling K at unit footprint per block centre (Hb*Wb,): from the partner planes (beyond the view
        too) and the curved partners. [1]

        It picks each surface's far blocks for its albedo: the blocks next to an edge have no facing block pairs
        (too close for a pair) but much coupling.
        """
        return self.plane_coupling_at_blocks + sum((group.coupling_at_blocks for group in self.pair_groups),
                                                   np.zeros_like(self.plane_coupling_at_blocks))

    def block_gain(self, area_m2: float, albedo: NDArray) -> NDArray[np.float64]:
        """The amplitude gain |1 + ratio| (F6) per block (Hb*Wb,), mean over the frequencies, at footprint
        ``area_m2`` [m^2] and albedos ``albedo`` (Hb*Wb,): the light the partner planes and curved partners send
        back to the block's centre, capped as in (F5)."""
        phasor = self.plane_phasor_at_blocks(albedo)
        two_bounce = self.bounces_phasor_at_blocks(albedo)
        if two_bounce is not None:
            phasor += two_bounce
        for group in self.pair_groups:
            phasor += group.phasors(albedo)
        return np.abs(1.0 + area_m2 * phasor / np.maximum(area_m2 * self.coupling_at_blocks, 1.0)[:, None]).mean(1)

    def plane_phasor_at_blocks(self, albedo: NDArray) -> NDArray[np.complex128]:
        """S_f (Hb*Wb, F) (F5) the partner planes give each block's centre for the albedos per block ``albedo``."""
        partner_albedo = albedo[self.partners.partner_block]
        return albedo[:, None] * np.einsum("p,npf->nf", partner_albedo, self.unit_plane_phasor_at_blocks)

    def bounces_phasor_at_blocks(self, albedo: NDArray) -> NDArray[np.complex128] | None:
        """The S_f (Hb*Wb, F) of the light among the partner planes, two bounces (F16) and three (F17), each block's
        centre gets for the albedos per block ``albedo`` (Hb*Wb,), None where the scan has no such light."""
        if self.unit_bounces_at_blocks is None:
            return None
        return albedo[:, None] * self.unit_bounces_at_blocks.phasor(albedo[self.partners.partner_block])


class PixelCoupling:
    """The unit-footprint multipath phasor S_f (n, F) and white coupling K (n,) (F5) of some pixels, for any albedos.

    Flat partners come from the scan's :class:`PlaneCoupling`, each pixel on its own surface's plane: worked
    out at the block centres and interpolated (:func:`_pixel_phasors`), and per pixel where the interpolation
    would reach a block of another surface or of none (the coupling changes fastest there, at an edge). Curved
    partners, and every partner of a pixel on no plane (against a reference depth any surface is measured),
    keep their block pairs (:class:`BlockPhasors`). Each pixel's surface is the one of its block or the
    blocks around it whose plane lies nearest its measured range.

    Parameters
    ----------
    plane : PlaneCoupling
        The scan's side.
    pixels : NDArray
        Flat pixel indices (n,).
    measured_range : NDArray
        Their highest-frequency range (n,). [m]
    frequencies_hz : tuple[float, ...] | None
        Those of the exact per-pixel sums, the scan's by default; :meth:`at_block_sums` then takes the block
        sums of the same frequencies. [Hz]
    """

    def __init__(self, plane: PlaneCoupling, pixels: NDArray, measured_range: NDArray,
                 frequencies_hz: tuple[float, ...] | None = None):
        self.plane, self.blocks = plane, plane.blocks
        blocks, partners = plane.blocks, plane.partners
        ys, xs = np.divmod(pixels, blocks.shape[1])
        b = blocks.block_pixels
        self.rays = plane.scan.pixel_rays(ys, xs)
        self.coordinates = blocks.pixel_coordinates(pixels)
        self.own_block = (ys // b) * plane.grid.shape[1] + xs // b
        self.surface = partners.nearest_surface(self.rays, measured_range, ys // b, xs // b, plane.grid)
        self.exact = partners.near_other_surface(self.coordinates, self.surface, plane.grid)
        at_points = plane.at_points if frequencies_hz is None else functools.partial(
            partners.at_points, frequencies_hz=frequencies_hz, speed_of_light_m_per_s=plane.speed_of_light_m_per_s)
        self.exact_unit_plane_phasor, exact_kappa = at_points(self.rays[self.exact], self.surface[self.exact])
        self.exact_plane_coupling = exact_kappa.sum(1)
        self.on_plane = np.isin(self.surface, list(partners.planes))

    def __call__(self, albedo: NDArray) -> tuple[NDArray[np.complex128], NDArray[np.float64]]:
        """S_f (n, F) and K (n,) of the pixels for the albedos per block ``albedo`` (Hb*Wb,)."""
        return self.at_block_sums(albedo, self.plane.plane_phasor_at_blocks(albedo),
                                  [group.phasors(albedo) for group in self.plane.pair_groups],
                                  self.plane.bounces_phasor_at_blocks(albedo))

    def at_block_sums(self, albedo: NDArray, plane_phasor: NDArray, pair_phasors: list[NDArray],
                      two_bounce_phasor: NDArray | None = None) -> tuple[NDArray[np.complex128], NDArray[np.float64]]:
        """:meth:`__call__` with the block centres' sums for ``albedo`` given (the partner planes' ``plane_phasor``,
        those of each of the plane's pair groups and the two bounces' ``two_bounce_phasor``, None: none), so that
        many sets of pixels can share them.

        The two bounces are interpolated from the block centres at every pixel on a plane, near an edge too: their
        light falls as 1 / r^2 per leg, not as the single bounce's 1 / r^4, and changes little across a block."""
        plane = self.plane
        phasor, kappa = _pixel_phasors(self.blocks, plane_phasor, plane.plane_coupling_at_blocks, self.coordinates)
        partner_albedo = albedo[plane.partners.partner_block]
        own = albedo[self.own_block[self.exact]]
        phasor[self.exact] = own[:, None] * np.einsum("p,npf->nf", partner_albedo, self.exact_unit_plane_phasor)
        kappa[self.exact] = self.exact_plane_coupling
        for group, pair_phasor in zip(plane.pair_groups, pair_phasors, strict=True):
            rows = self.on_plane if group.receivers_on_plane else ~self.on_plane
            coordinates = (self.coordinates[0][rows], self.coordinates[1][rows])
            rows_phasor, rows_kappa = _pixel_phasors(self.blocks, pair_phasor, group.coupling_at_blocks, coordinates)
            phasor[rows] += rows_phasor
            kappa[rows] += rows_kappa
        if two_bounce_phasor is not None:
            coordinates = (self.coordinates[0][self.on_plane], self.coordinates[1][self.on_plane])
            phasor[self.on_plane] += np.stack([self.blocks.to_pixels(two_bounce_phasor[:, k].real, coordinates)
                                               + 1j * self.blocks.to_pixels(two_bounce_phasor[:, k].imag, coordinates)
                                               for k in range(two_bounce_phasor.shape[1])], axis=1)
        return phasor, kappa


def _pixel_phasors(blocks: FacingBlocks, unit_phasor: NDArray, unit_kappa: NDArray,
                   coordinates: tuple[NDArray, NDArray]) -> tuple[NDArray[np.complex128], NDArray[np.float64]]:
    """Unit-footprint phasors (n, F) and white coupling (n,) at pixel coordinates, from the block values.

    The coupling is interpolated as a coupling (:meth:`FacingBlocks.coupling_to_pixels`: 1 / sqrt(K) is linear in
    the distance from an edge), the phasor as K times its (smooth) ratio to K.
    """
    has = unit_kappa > 0
    kappa = blocks.coupling_to_pixels(unit_kappa, coordinates)
    ratio = np.where(has[:, None], unit_phasor / np.where(has, unit_kappa, 1.0)[:, None], 0.0)
    phasor = np.stack([blocks.to_pixels(ratio[:, k].real, coordinates) + 1j * blocks.to_pixels(ratio[:, k].imag,
                                                                                               coordinates)
                       for k in range(ratio.shape[1])], axis=1)
    return phasor * kappa[:, None], kappa
