"""A correction model's geometric inputs per pixel (rho_ABA, d_AB) from the partner planes at a footprint."""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from mpi_lidar.config import SensorConfig
from mpi_lidar.correction.footprint._albedo import block_albedo, light_free_albedo, partner_albedo
from mpi_lidar.correction.footprint._coupling import PixelCoupling, PlaneCoupling
from mpi_lidar.correction.footprint._surfaces import SurfaceLabels, surface_labels
from mpi_lidar.scans.geometry import BAND_PIXELS, EquivalentRhoAba, FacingBlocks
from mpi_lidar.scans.scan import Scan


class PlaneModelInputs:
    """A correction model's geometric inputs per pixel from the partner planes: the rho_ABA and d_AB of the
    surface facing the sensor that shows the pixel's multipath (:meth:`FacingBlocks.equivalent_rho_aba` says
    why that is what a model trained on facing surfaces needs).

    At footprint A the two-path ratio of a pixel is (F5) (:class:`PixelCoupling`). At the lowest frequency f,

    (F15)  rho_ABA = |ratio_f| / (rho_A cos_i),   d_AB = arg(ratio_f) mod 2 pi / (4 pi f / c)  [m],

    the ratio's magnitude over the albedo rho_A cos_i the pixel's amplitude shows, and its phase over the
    wavenumber. Evaluated at each pixel on its own surface's plane, near an edge by the exact
    sums over the partners' patches, this follows the coupling's steep rise towards an edge that sums from
    block centre to block centre smear (1.2-2x high a few centimetres out, low at the edge). Pixels on no
    plane, or whose point on it no partner plane lights, keep the block estimates ``fallback``. Read-only
    once made, so threads may share it.
    """

    # Incidence cosines below this are taken as this: a surface seen edge-on has no albedo to speak of.
    MIN_COS_I = 0.05

    def __init__(self, fallback: EquivalentRhoAba, plane: PlaneCoupling | None = None, albedo: NDArray | None = None,
                 area_m2: float = 0.0):
        """``fallback``: the blocks' estimates; ``plane``: the scan's partner planes (None: the blocks' estimates
        everywhere); ``albedo``: the albedo per block (Hb*Wb,) [1]; ``area_m2``: the footprint A_fp [m^2]."""
        self.fallback, self.plane, self.albedo, self.area_m2 = fallback, plane, albedo, area_m2
        if plane is not None:
            assert albedo is not None, "the albedos the planes' inputs are for"
            # Only the lowest frequency's sums are needed: a quarter of the per-pixel work of all four.
            lowest = int(np.argmin(plane.scan.frequencies_hz))
            self.frequency_hz = float(plane.scan.frequencies_hz[lowest])
            self.plane_phasor = plane.plane_phasor_at_blocks(albedo)[:, [lowest]]
            self.pair_phasors = [group.phasors(albedo)[:, [lowest]] for group in plane.pair_groups]
            two_bounce = plane.bounces_phasor_at_blocks(albedo)
            self.two_bounce_phasor = None if two_bounce is None else two_bounce[:, [lowest]]
            self.wavenumber = 4 * np.pi * self.frequency_hz / plane.speed_of_light_m_per_s

    def pixels(self, pixels: NDArray, measured_range: NDArray) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """rho_ABA (n,) [1] and d_AB (n,) [m] (F15) of flat pixel indices (n,) whose highest-frequency range is
        ``measured_range`` (n,) [m]: 0 and NaN where no partner."""
        if self.plane is None or self.albedo is None or pixels.size == 0:
            return self.fallback.pixels(pixels)
        coupling, ratio = self._ratio(pixels, measured_range)
        own = self.albedo[coupling.own_block]
        # A pixel right at an edge may meet its plane just past the partner's face (no coupling there): the
        # blocks' estimate stands for it.
        planar = coupling.on_plane & (own > 0) & (np.abs(ratio) > 0)
        rho_aba, d_ab = np.empty(pixels.size), np.empty(pixels.size)
        rho_aba[~planar], d_ab[~planar] = self.fallback.pixels(pixels[~planar])
        normals = self._normals(self.plane, coupling.surface[planar])
        cos_i = np.maximum(np.abs(np.einsum("ni,ni->n", normals, coupling.rays[planar])), self.MIN_COS_I)
        rho_aba[planar] = np.abs(ratio[planar]) / (own[planar] * cos_i)
        d_ab[planar] = np.where(rho_aba[planar] > 0, np.mod(np.angle(ratio[planar]), 2 * np.pi) / self.wavenumber,
                                np.nan)
        return rho_aba, d_ab

    def bias_m(self, pixels: NDArray, measured_range: NDArray, frequency_hz: float) -> NDArray[np.float64]:
        """The depth bias [m] (n,) the partner planes predict at ``frequency_hz`` [Hz] for flat pixel indices (n,)
        whose highest-frequency range is ``measured_range`` (n,) [m]; 0 where no partner plane lights a pixel (or
        the scan has none).

        One path through the lowest frequency's ratio (F15): its magnitude and its d_AB, at the phase
        4 pi f d_AB / c of ``frequency_hz`` (F6). The light of several partners and of two bounces adds up to such
        a path to within a millimetre or two of the 31.25 MHz bias on the rendered rooms."""
        bias = np.zeros(pixels.size)
        if self.plane is None or self.albedo is None or pixels.size == 0:
            return bias
        coupling, ratio = self._ratio(pixels, measured_range)
        lit = coupling.on_plane & (np.abs(ratio) > 0)
        speed_of_light = self.plane.speed_of_light_m_per_s
        # d_AB = phase / wavenumber, so the phase at another frequency scales with it.
        phase = np.mod(np.angle(ratio[lit]), 2 * np.pi) * (frequency_hz / self.frequency_hz)
        metres_per_rad = speed_of_light / (4 * np.pi * frequency_hz)
        bias[lit] = np.angle(1.0 + np.abs(ratio[lit]) * np.exp(1j * phase)) * metres_per_rad
        return bias

    def light_parts(self, pixels: NDArray, measured_range: NDArray) -> tuple[NDArray[np.complex128],
                                                                            NDArray[np.complex128]]:
        """The multipath ratio (n,) (F5) at the lowest frequency of flat pixel indices (n,) whose highest-frequency
        range is ``measured_range`` (n,) [m], in two parts: the partners' single bounces, and the light among the
        partner planes ((F16), (F17)); their sum is the ratio the inputs rest on. Zero where no partner plane
        lights a pixel (or the scan has none): what a light budget compares with a render's own."""
        single, among = np.zeros(pixels.size, dtype=np.complex128), np.zeros(pixels.size, dtype=np.complex128)
        if self.plane is None or self.albedo is None or pixels.size == 0:
            return single, among
        coupling, ratio = self._ratio(pixels, measured_range)
        bounced, kappa = coupling.at_block_sums(self.albedo, self.plane_phasor, self.pair_phasors, None)
        lit = coupling.on_plane
        single[lit] = (self.area_m2 * bounced[:, 0] / np.maximum(self.area_m2 * kappa, 1.0))[lit]
        among[lit] = ratio[lit] - single[lit]
        return single, among

    def _ratio(self, pixels: NDArray, measured_range: NDArray) -> tuple[PixelCoupling, NDArray[np.complex128]]:
        """The pixels' coupling and their multipath ratio (n,) (F5) at the lowest frequency."""
        assert self.plane is not None and self.albedo is not None
        coupling = PixelCoupling(self.plane, pixels, measured_range, (self.frequency_hz,))
        phasor, kappa = coupling.at_block_sums(self.albedo, self.plane_phasor, self.pair_phasors,
                                               self.two_bounce_phasor)
        return coupling, self.area_m2 * phasor[:, 0] / np.maximum(self.area_m2 * kappa, 1.0)

    @staticmethod
    def _normals(plane: PlaneCoupling, surfaces: NDArray) -> NDArray[np.float64]:
        """The unit normal (n, 3) of each pixel's surface plane."""
        planes = plane.partners.planes
        normals = np.zeros((surfaces.size, 3))
        for surface in np.unique(surfaces):
            normals[surfaces == surface] = planes[int(surface)].normal
        return normals


def plane_model_inputs(scan: Scan, blocks: FacingBlocks, sensor: SensorConfig, area_m2: float,
                       surfaces: SurfaceLabels | None = None, measured_albedo: NDArray | None = None,
                       tile_pixels: int = BAND_PIXELS, white_surfaces: bool = False,
                       fitted_planes: dict[int, NDArray] | None = None) -> PlaneModelInputs:
    """A scan's :class:`PlaneModelInputs` at footprint ``area_m2`` [m^2].

    Per pixel from the partner planes, and where a pixel lies on no plane from the facing blocks, each partner
    weighted by its surface's albedo (from the amplitude) over the incidence cosine
    (:meth:`mpi_lidar.scans.geometry.FacingBlocks.equivalent_rho_aba`). Without facing blocks or at a footprint of
    zero, the blocks' estimate of no multipath. ``surfaces`` (:func:`surface_labels`) and ``measured_albedo``
    (:func:`block_albedo`, its tiles of ``tile_pixels``) are worked out where not given. ``white_surfaces``: the
    albedos are taken, not measured (:func:`white_albedo`, a scan whose amplitude unit is not known), so no
    multipath's gain is taken off them. ``fitted_planes`` (u [1/m] by flat-surface label, :func:`unbent_planes`)
    replace those surfaces' planes through their blocks.
    """
    if blocks.pairs.a.size == 0 or area_m2 <= 0:
        return PlaneModelInputs(blocks.equivalent_rho_aba(0.0, np.zeros(blocks.usable.size)))
    if measured_albedo is None:
        measured_albedo = block_albedo(scan, blocks, sensor, tile_pixels)
    if surfaces is None:
        surfaces = surface_labels(blocks)
    fallback = blocks.equivalent_rho_aba(area_m2, partner_albedo(blocks, measured_albedo, surfaces.components))
    plane = PlaneCoupling(scan, blocks, surfaces, sensor, fitted_planes)
    albedo = (measured_albedo if white_surfaces
              else light_free_albedo(plane, measured_albedo, surfaces.components, area_m2))
    return PlaneModelInputs(fallback, plane, albedo, area_m2)
