"""Self-calibration of the receiver footprint: a scan measures its own multipath strength.

How much light a facing surface sends back scales with one sensor constant, the effective receiver footprint
A_fp (:mod:`mpi_lidar.physics.coupling`). A scan holds the evidence for it: on two surfaces that face each
other the raw depth drifts away from the surfaces' planes towards their shared edge, in proportion to A_fp
and with the shape the geometry predicts, while far from the edge the surfaces are unbiased.

:func:`estimate_footprint` measures A on the flat surfaces of the scan: connected blocks of
:class:`mpi_lidar.scans.geometry.FacingBlocks` whose planes agree, without the blocks that bend away from them
(curved surfaces, the strongest bias right at an edge) and without strips that have no pixels far from their
partners. The model of every pixel and frequency f is the renderer's two-path model at unit footprint:
ratio = A S_f, S_f = rho_A sum_B rho_B kappa_B e^{j 4 pi f r_AB / c}, capped like it at kappa = 1, with the
depth bias (c / 4 pi f) arg(1 + ratio). The flat partners B are planes continued beyond the field of view
(:mod:`mpi_lidar.correction.plane_partners`), each pixel on its own surface's plane (:class:`PixelCoupling`).
The albedos rho come from each surface's amplitude on the blocks the model couples least to its partners
(Gamma = Gamma_R rho cos_i / d^2), less the light the multipath adds there at the current estimate (the
partner planes beyond the view included), so dark partners predict less multipath than white ones.

Each surface's plane is fitted to the share of its pixels with the least predicted coupling (the anchors),
after the predicted bias is taken off, and A is fitted to the other pixels' depth over their plane: a
Gauss-Newton fit weighted by the moment model's noise at each pixel's amplitude, with Huber weights against
outliers, whose derivative includes the planes' own motion with A and which starts from the best footprint
of a coarse grid (the residuals are not convex in A where the multipath is strong). A first round on every
third pixel gives the second, on every pixel, its start, its albedos and its partner planes (strong
multipath bends each surface near its partners, and the planes through its blocks meet at too sharp an
angle); a third follows where the second's estimate moves the albedos by more than 2 %. The
uncertainty is the statistical one (the fit pixels' noise and the anchors' through their planes, scaled by
the robust spread of the standardized residuals) combined with a systematic share of the estimate, the
spread measured on rendered corners.

Multipath adds light as well as range: the same model fitted to the amplitude of the second round (the gain
|1 + ratio|, one albedo per surface eliminated) gives a second estimate. Where the two differ by more than a
factor of three the scan is not what the model describes and the estimate is not significant; where they
agree, the estimate is their mean in log A weighted by their relative uncertainties. The amplitude weighs the
more where the multipath is strong (the planes the depth is measured against take up part of a strong bias:
on the rendered corners at 0.1 m^2 the depth alone read 0.54-1.07x), the depth where the coupling is weak
and the amplitude has little leverage on A. With a reference depth (``reference=True``) the depth residual is
measured against it directly, the planes are not needed, and the amplitude is not used.
"""

from __future__ import annotations

import functools
from dataclasses import asdict, dataclass, replace

import numpy as np
from numpy.typing import NDArray

from mpi_lidar.config import SensorConfig
from mpi_lidar.correction.plane_partners import PlanePartners
from mpi_lidar.correction.validity import quadrature_noise_v2
from mpi_lidar.scans.geometry import BAND_PIXELS, EquivalentRhoAba, FacingBlocks, nanmedian_last, to_blocks
from mpi_lidar.scans.scan import Scan
from mpi_lidar.threads import on_cores

# A surface is a connected set of blocks whose normals agree to this [deg] and whose centres lie on each
# other's planes (a depth step is another surface) ...
NEIGHBOUR_ANGLE_DEG = 20.0
# ... and whose blocks bend from the surface's mean normal by less than this [deg]; bending blocks are left out.
SURFACE_ANGLE_DEG = 25.0
MIN_SURFACE_BLOCKS = 3
# Share of the pixels, those with the least predicted coupling, that fix the surfaces' planes (anchors); a
# surface with fewer anchors than this has no plane to measure against.
ANCHOR_SHARE = 0.4
MIN_ANCHOR_PIXELS = 50
# A surface whose anchors lie along a line leaves its plane free to turn about it: the condition number of
# the plane's normal matrix shows it (a few 10^3 on the boards of the benchmarks, above 10^17 on a line).
MAX_PLANE_CONDITION = 1e8
# Pixels the fit uses at most: a subsample on a regular stride keeps the cost a small share of correction
# (the systematic uncertainty below dwarfs the statistical one long before).
MAX_FIT_PIXELS = 12_000
# Rows whose predicted multipath ratio A K exceeds this are left out (there the cap at kappa = 1 leaves the
# depth nothing to say about A).
MAX_FIT_COUPLING = 2.0
# Gauss-Newton: iterations in all, the first of them plain least squares (before A is near, the multipath
# itself looks like an outlier), then Huber weights at this many robust sigmas (nothing beyond six).
MAX_ITERATIONS = 20
PLAIN_ITERATIONS = 4
HUBER_K = 2.0
# The fit stops once a step changes A by less than this share of it: far below the systematic uncertainty.
CONVERGED_STEP = 1e-3
# The amplitude's fit stops at a 1 % step: a tenth of its systematic uncertainty.
AMPLITUDE_STEP = 1e-2
# A round before the last sets only the next one's start, albedos and partner planes: a 1 % step ends it.
EARLY_ROUND_STEP = 1e-2
# The albedos less the multipath's gain: fixed-point iterations at one footprint (the gain grows with them) ...
ALBEDO_ITERATIONS = 3
# ... and rounds of the fit at most, another only where the last estimate moves the albedos by more than this.
ALBEDO_ROUNDS = 2
ALBEDO_STEP = 0.02
# Relative step of A for the planes' derivative.
PLANE_STEP = 1e-3
# Footprints [m^2] the depth fit may start from: 0 and 1 mm^2 ... 0.5 m^2 in factors of two.
START_GRID_M2 = (0.0, *(1e-3 * 2.0**k for k in range(10)))
# The first of the two rounds sets only the second's start, albedos and partner planes: every third pixel.
FIRST_ROUND_STRIDE = 3
# Systematic uncertainty of an estimate, as a share of it: the spread of estimate / truth on rendered corners
# (the depth's 0.19 and the amplitude's 0.08 rms in log where the edge multipath exceeds 2 mm, 0.35 and 0.12
# between 0.5 and 2 mm). The depth's planes take up part of a strong bias (they tilt towards the edge),
# while the amplitude's gain needs no plane of its own beyond each pixel's angle of incidence.
DEPTH_SYSTEMATIC_SHARE = 0.25
AMPLITUDE_SYSTEMATIC_SHARE = 0.1
# ... and, for the amplitude, an error in log amplitude that no footprint explains (the angle of incidence from
# fitted planes, partners beyond the view): 0.7 %, over the fit's leverage d log|1 + ratio| / dA. It is the rms,
# over the main set's corners, of |A_amplitude - A_true| times that leverage; a wide corner's weak coupling
# has little leverage and leaves the estimate to the depth.
AMPLITUDE_SYSTEMATIC_LOG = 7e-3
# The amplitude must tell the same footprint as the depth to this factor.
AMPLITUDE_AGREEMENT = 3.0
# No receiver footprint reaches this [m^2]: a larger estimate is no measurement.
MAX_PLAUSIBLE_M2 = 1.0
# The estimate is used only when it is this many standard deviations above zero ...
MIN_SIGNIFICANCE = 3.0
# ... and rests on at least this many pixels with a facing partner.
MIN_INFORMATIVE_PIXELS = 200


@dataclass(frozen=True)
class FootprintEstimate:
    """The footprint a scan (or several) measured, and how sure it is.

    ``area_m2`` is the estimate of A_fp [m^2] (NaN where nothing could be measured), ``sigma_m2`` its
    standard deviation [m^2] (inf then); ``pixels`` the pixels with a facing partner the fit rests on,
    ``surfaces`` the flat surfaces fitted, ``scans`` how many scans were pooled; ``method`` is "planes"
    (the scan's own surfaces) or "reference" (raw depth against a reference depth).
    """

    area_m2: float
    sigma_m2: float
    pixels: int
    surfaces: int
    method: str = "planes"
    scans: int = 1

    @property
    def significance(self) -> float:
        """Estimate over its standard deviation (0 where nothing was measured)."""
        if not np.isfinite(self.area_m2) or not np.isfinite(self.sigma_m2) or self.sigma_m2 <= 0:
            return 0.0
        return self.area_m2 / self.sigma_m2

    @property
    def significant(self) -> bool:
        """Whether the estimate may decide pixels: clearly above zero, on enough pixels."""
        return self.significance >= MIN_SIGNIFICANCE and self.pixels >= MIN_INFORMATIVE_PIXELS

    def upper_m2(self) -> float:
        """Upper bound [m^2]: the estimate plus two standard deviations (inf where nothing was measured)."""
        if not np.isfinite(self.sigma_m2):
            return float("inf")
        return max(self.area_m2, 0.0) + 2.0 * self.sigma_m2

    def to_dict(self) -> dict[str, object]:
        """JSON-ready summary (non-finite numbers as None)."""
        out: dict[str, object] = {k: (v if not isinstance(v, float) or np.isfinite(v) else None)
                                  for k, v in asdict(self).items()}
        out.update(significance=round(self.significance, 2), significant=self.significant)
        return out


NOTHING_MEASURED = FootprintEstimate(float("nan"), float("inf"), 0, 0)


def estimate_footprint(scan: Scan, blocks: FacingBlocks, valid: NDArray, sensor: SensorConfig, *,
                       reference: bool = False, max_pixels: int = MAX_FIT_PIXELS,
                       measured_albedo: NDArray | None = None) -> FootprintEstimate:
    """The receiver footprint A_fp [m^2] that best explains the scan's depth near facing surfaces.

    ``blocks`` is the scan's :func:`mpi_lidar.scans.geometry.facing_blocks` (from its highest-frequency
    depth), ``valid`` a bool (H*W,) of the pixels whose measurements can be trusted. With ``reference``
    the scan's reference depth replaces the fitted planes (it must have one). ``measured_albedo`` is the
    scan's :func:`block_albedo`, where the caller has it already.
    """
    if blocks.pairs.a.size == 0:
        return NOTHING_MEASURED
    components, labels = surface_labels(blocks)
    unit_kappa = np.bincount(blocks.index[blocks.pairs.a], blocks.pairs.kappa(1.0), minlength=blocks.usable.size)
    # Against a reference every surface, flat or not, measures the bias; the partners are the flat surfaces.
    fitted = np.where(blocks.usable.ravel(), 0, -1) if reference else labels
    pixels = _fit_pixels(blocks, fitted, unit_kappa, valid, max_pixels)
    if pixels.size == 0:
        return NOTHING_MEASURED
    ys, xs = np.divmod(pixels, blocks.shape[1])
    depth = scan.depth[:, ys, xs].astype(np.float64).T
    amplitude = scan.amplitude[:, ys, xs].astype(np.float64).T
    freqs = np.asarray(scan.frequencies_hz, dtype=np.float64)
    metres_per_rad = sensor.speed_of_light_m_per_s / (4 * np.pi * freqs)
    sigma = quadrature_noise_v2(sensor, scan.frequencies_hz, amplitude) / np.maximum(amplitude, 1e-12)
    sigma = np.maximum(sigma * metres_per_rad, 1e-5)
    usable = np.isfinite(depth).all(1) & np.isfinite(sigma).all(1)
    reference_depth = scan.reference_depth.ravel()[pixels].astype(np.float64) if reference else None
    method = "reference" if reference else "planes"

    def pixel_coupling(rows: NDArray, planes: dict[int, NDArray] | None = None) -> PixelCoupling:
        return PixelCoupling(PlaneCoupling(scan, blocks, components, labels, sensor, planes), pixels[rows],
                             depth[rows, -1])

    def problem(rows: NDArray, coupling: PixelCoupling, albedo: NDArray) -> _Problem:
        phasor, kappa = coupling(albedo)
        return _Problem(depth[rows], sigma[rows], phasor, kappa, metres_per_rad, amplitude[rows] / sensor.gamma_r_v2,
                        coupling.rays, coupling.surface, None if reference_depth is None else reference_depth[rows])

    if measured_albedo is None:
        measured_albedo = block_albedo(scan, blocks, sensor)
    rows = np.flatnonzero(usable)
    first_rows = rows[::FIRST_ROUND_STRIDE]
    first_coupling = pixel_coupling(first_rows)
    first_albedo = first_coupling.plane.light_free_albedo(measured_albedo, components, 0.0)
    first_problem = problem(first_rows, first_coupling, first_albedo)
    first = first_problem.solve(method, with_amplitude=False, tolerance=EARLY_ROUND_STEP)
    if not (np.isfinite(first.area_m2) and first.area_m2 > 0):  # no multipath to correct for: one round on all
        return problem(rows, pixel_coupling(rows), first_albedo).solve(method)
    # Strong multipath bends each surface near its partners, so the planes through its blocks meet at too
    # sharp an angle and predict too much coupling; the planes of the later rounds rest on the anchors less the
    # bias predicted at the first estimate.
    last_coupling = pixel_coupling(rows, None if reference else first_problem.anchored_planes(first.area_m2))
    # Multipath adds light, so the amplitude overstates the albedos (at strong multipath on the whole of a
    # surface near its partners): each round's albedos are the measured ones less the gain the multipath gives
    # at the estimate before it, and a round that moves them by more than ALBEDO_STEP is followed by another.
    area, albedo = first.area_m2, None
    for _ in range(ALBEDO_ROUNDS):
        light_free = last_coupling.plane.light_free_albedo(measured_albedo, components, area)
        if albedo is not None and _largest_change(albedo, light_free) <= ALBEDO_STEP:
            break
        albedo = light_free
        estimate = problem(rows, last_coupling, albedo).solve(method, start_m2=area)
        if not (np.isfinite(estimate.area_m2) and estimate.area_m2 > 0):
            break
        area = estimate.area_m2
    return estimate


def _largest_change(before: NDArray, after: NDArray) -> float:
    """The largest relative change from ``before`` to ``after`` where ``before`` is positive."""
    positive = before > 0
    return float(np.max(np.abs(after[positive] / before[positive] - 1.0), initial=0.0))


class PlaneCoupling:
    """A scan's side of :class:`PixelCoupling`: the partner planes (:class:`PlanePartners`), their unit-footprint
    sums at the block centres and the block pairs they do not describe, worked out once for any pixels.

    Read-only once made, so threads may share it.
    """

    def __init__(self, scan: Scan, blocks: FacingBlocks, components: NDArray, labels: NDArray, sensor: SensorConfig,
                 fitted: dict[int, NDArray] | None = None):
        self.scan, self.blocks = scan, blocks
        self.speed_of_light_m_per_s = sensor.speed_of_light_m_per_s
        self.partners = PlanePartners(scan, blocks, components, labels, fitted)
        self.grid = labels.reshape(blocks.usable.shape)
        self.at_points = functools.partial(self.partners.at_points, frequencies_hz=scan.frequencies_hz,
                                           speed_of_light_m_per_s=sensor.speed_of_light_m_per_s)
        block_rows, block_columns = np.divmod(np.arange(labels.size), self.grid.shape[1])
        centre_range = np.linalg.norm(blocks.centres.reshape(-1, 3), axis=1)
        block_surface = self.partners.nearest_surface(self.partners.block_rays, centre_range, block_rows,
                                                      block_columns, self.grid)
        self.block_plane_phasor, block_kappa = self.at_points(self.partners.block_rays, block_surface)
        self.block_plane_kappa = block_kappa.sum(1)
        # The block pairs of receivers on a plane with curved partners, and of receivers on no plane.
        self.pair_sums = [(BlockPhasors(blocks, scan.frequencies_hz, sensor.speed_of_light_m_per_s, pairs),
                           np.bincount(pairs[0], pairs[2], minlength=blocks.usable.size), on_plane)
                          for pairs, on_plane in ((self.partners.curved, True), (self.partners.off_plane, False))
                          if pairs[0].size]

    def light_free_albedo(self, measured: NDArray, components: NDArray, area: float) -> NDArray[np.float64]:
        """The albedo per surface (:func:`surface_albedo`, far blocks by :attr:`block_kappa`) of the blocks'
        ``measured`` albedos (Hb*Wb,) divided by the gain the multipath gives them at footprint ``area`` (a
        gain that itself grows with the albedos)."""
        kappa = self.block_kappa
        albedo = surface_albedo(measured, components, kappa)
        for _ in range(ALBEDO_ITERATIONS if area > 0 else 0):
            albedo = surface_albedo(measured / self.block_gain(area, albedo), components, kappa)
        return albedo

    @functools.cached_property
    def block_kappa(self) -> NDArray[np.float64]:
        """White coupling at unit footprint per block centre (Hb*Wb,): from the partner planes (beyond the view
        too) and the curved partners. It picks each surface's far blocks for its albedo: the blocks next to an
        edge have no facing block pairs (too close for a pair) but much coupling."""
        return self.block_plane_kappa + sum((block_kappa for _, block_kappa, _ in self.pair_sums),
                                            np.zeros_like(self.block_plane_kappa))

    def block_gain(self, area: float, albedo: NDArray) -> NDArray[np.float64]:
        """The amplitude gain |1 + ratio| per block (Hb*Wb,), mean over the frequencies, at footprint ``area``
        and albedos ``albedo`` (Hb*Wb,): the light the partner planes and curved partners send back to the
        block's centre, capped like :meth:`_Problem.bias`."""
        phasor = self.block_plane_phasor_for(albedo)
        for phasors, _, _ in self.pair_sums:
            phasor += phasors(albedo)
        return np.abs(1.0 + area * phasor / np.maximum(area * self.block_kappa, 1.0)[:, None]).mean(1)

    def block_plane_phasor_for(self, albedo: NDArray) -> NDArray[np.complex128]:
        """S_f (Hb*Wb, F) the partner planes give each block's centre for the albedos per block ``albedo``."""
        partner_albedo = albedo[self.partners.partner_block]
        return albedo[:, None] * np.einsum("p,npf->nf", partner_albedo, self.block_plane_phasor)


class PixelCoupling:
    """The unit-footprint multipath phasor S_f (n, F) and white kappa (n,) of some pixels, for any albedos.

    Flat partners come from the scan's :class:`PlaneCoupling`, each pixel on its own surface's plane: worked
    out at the block centres and interpolated (:func:`_pixel_phasors`), and per pixel where the interpolation
    would reach a block of another surface or of none (the coupling changes fastest there, at an edge). Curved
    partners, and every partner of a pixel on no plane (against a reference depth any surface is measured),
    keep their block pairs (:class:`BlockPhasors`). Each pixel's surface is the one of its block or the
    blocks around it whose plane lies nearest its measured range.
    """

    def __init__(self, plane: PlaneCoupling, pixels: NDArray, measured_range: NDArray,
                 frequencies_hz: tuple[float, ...] | None = None):
        """``frequencies_hz``: those of the exact per-pixel sums, the scan's by default; :meth:`at_block_sums`
        then takes the block sums of the same frequencies."""
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
        self.exact_plane_phasor, exact_kappa = at_points(self.rays[self.exact], self.surface[self.exact])
        self.exact_plane_kappa = exact_kappa.sum(1)
        self.on_plane = np.isin(self.surface, list(partners.planes))

    def __call__(self, albedo: NDArray) -> tuple[NDArray[np.complex128], NDArray[np.float64]]:
        """S_f (n, F) and kappa (n,) of the pixels for the albedos per block ``albedo`` (Hb*Wb,)."""
        return self.at_block_sums(albedo, self.plane.block_plane_phasor_for(albedo),
                                  [phasors(albedo) for phasors, _, _ in self.plane.pair_sums])

    def at_block_sums(self, albedo: NDArray, block_plane_phasor: NDArray, pair_phasors: list[NDArray]
                      ) -> tuple[NDArray[np.complex128], NDArray[np.float64]]:
        """:meth:`__call__` with the block centres' sums for ``albedo`` given (the partner planes' and those of
        each of the plane's block pairs), so that many sets of pixels can share them."""
        plane = self.plane
        phasor, kappa = _pixel_phasors(self.blocks, block_plane_phasor, plane.block_plane_kappa, self.coordinates)
        partner_albedo = albedo[plane.partners.partner_block]
        own = albedo[self.own_block[self.exact]]
        phasor[self.exact] = own[:, None] * np.einsum("p,npf->nf", partner_albedo, self.exact_plane_phasor)
        kappa[self.exact] = self.exact_plane_kappa
        for (_, block_kappa, on_plane), pair_phasor in zip(plane.pair_sums, pair_phasors, strict=True):
            rows = self.on_plane if on_plane else ~self.on_plane
            coordinates = (self.coordinates[0][rows], self.coordinates[1][rows])
            rows_phasor, rows_kappa = _pixel_phasors(self.blocks, pair_phasor, block_kappa, coordinates)
            phasor[rows] += rows_phasor
            kappa[rows] += rows_kappa
        return phasor, kappa


class PlaneModelInputs:
    """A correction model's geometric inputs per pixel from the partner planes: the rho_ABA and d_AB of the
    surface facing the sensor that shows the pixel's multipath (:meth:`FacingBlocks.equivalent_rho_aba` says
    why that is what a model trained on facing surfaces needs).

    At footprint A the two-path ratio of a pixel is A S_f / max(A kappa, 1) (:class:`PixelCoupling`), with
    S_f = rho_A sum_B rho_B kappa_B e^{j 4 pi f r_AB / c}. Its magnitude at the lowest frequency over the
    albedo rho_A cos_i the pixel's amplitude shows is the equivalent rho_ABA, its phase over 4 pi f / c the
    A-B distance the bias sees. Evaluated at each pixel on its own surface's plane, near an edge by the exact
    sums over the partners' patches, this follows the coupling's steep rise towards an edge that sums from
    block centre to block centre smear (1.2-2x high a few centimetres out, low at the edge). Pixels on no
    plane, or whose point on it no partner plane lights, keep the block estimates ``fallback``. Read-only
    once made, so threads may share it.
    """

    # Incidence cosines below this are taken as this: a surface seen edge-on has no albedo to speak of.
    MIN_COS_I = 0.05

    def __init__(self, fallback: EquivalentRhoAba, plane: PlaneCoupling | None = None, albedo: NDArray | None = None,
                 area_m2: float = 0.0):
        self.fallback, self.plane, self.albedo, self.area_m2 = fallback, plane, albedo, area_m2
        if plane is not None:
            # Only the lowest frequency's sums are needed: a quarter of the per-pixel work of all four.
            lowest = int(np.argmin(plane.scan.frequencies_hz))
            self.frequency_hz = float(plane.scan.frequencies_hz[lowest])
            self.block_plane_phasor = plane.block_plane_phasor_for(albedo)[:, [lowest]]
            self.pair_phasors = [phasors(albedo)[:, [lowest]] for phasors, _, _ in plane.pair_sums]
            self.wavenumber = 4 * np.pi * self.frequency_hz / plane.speed_of_light_m_per_s

    def pixels(self, pixels: NDArray, measured_range: NDArray) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """rho_ABA (n,) and d_AB (n,) [m] of flat pixel indices (n,) whose highest-frequency range is
        ``measured_range`` (n,) [m]: 0 and NaN where no partner."""
        if self.plane is None or pixels.size == 0:
            return self.fallback.pixels(pixels)
        coupling = PixelCoupling(self.plane, pixels, measured_range, (self.frequency_hz,))
        phasor, kappa = coupling.at_block_sums(self.albedo, self.block_plane_phasor, self.pair_phasors)
        ratio = self.area_m2 * phasor[:, 0] / np.maximum(self.area_m2 * kappa, 1.0)
        own = self.albedo[coupling.own_block]
        # A pixel right at an edge may meet its plane just past the partner's face (no coupling there): the
        # blocks' estimate stands for it.
        planar = coupling.on_plane & (own > 0) & (np.abs(ratio) > 0)
        rho_aba, d_ab = np.empty(pixels.size), np.empty(pixels.size)
        rho_aba[~planar], d_ab[~planar] = self.fallback.pixels(pixels[~planar])
        normals = self._normals(coupling.surface[planar])
        cos_i = np.maximum(np.abs(np.einsum("ni,ni->n", normals, coupling.rays[planar])), self.MIN_COS_I)
        rho_aba[planar] = np.abs(ratio[planar]) / (own[planar] * cos_i)
        d_ab[planar] = np.where(rho_aba[planar] > 0, np.mod(np.angle(ratio[planar]), 2 * np.pi) / self.wavenumber,
                                np.nan)
        return rho_aba, d_ab

    def _normals(self, surfaces: NDArray) -> NDArray[np.float64]:
        """The unit normal (n, 3) of each pixel's surface plane."""
        planes = self.plane.partners.planes
        normals = np.zeros((surfaces.size, 3))
        for surface in np.unique(surfaces):
            normals[surfaces == surface] = planes[int(surface)][0]
        return normals


def block_albedo(scan: Scan, blocks: FacingBlocks, sensor: SensorConfig,
                 tile_pixels: int = BAND_PIXELS) -> NDArray[np.float64]:
    """Albedo per block (Hb*Wb,) from the amplitude of its inlier pixels: Gamma d^2 / (Gamma_R cos_i).

    The median over the block's inliers of the amplitude (mean over frequencies), clipped to 0.01-1.5;
    0 for blocks without a plane. Worked out a tile of whole blocks, about ``tile_pixels``, at a time
    (:meth:`FacingBlocks.tiles`), so its temporaries stay within the correction's tiles.
    """
    rays = scan.ray_rows()

    def band_albedo(band: list[tuple[slice, slice]]) -> NDArray[np.float64]:
        band_rays = rays[band[0][0]]
        return np.concatenate([_tile_albedo(scan, blocks, band_rays[:, columns], rows, columns, sensor)
                               for rows, columns in band], axis=1)

    bands = blocks.tiles(tile_pixels)
    # Bands of a scan in memory on one thread per core; a scan in its store is read one band after the other
    # (it keeps one band of decoded rows, which two threads would take from each other).
    found = np.concatenate(on_cores(band_albedo, bands) if scan.in_memory() else [band_albedo(band) for band in bands])
    found = np.where(blocks.usable & np.isfinite(found), np.clip(found, 0.01, 1.5), 0.0)
    return found.ravel()


def _tile_albedo(scan: Scan, blocks: FacingBlocks, rays: NDArray, rows: slice, columns: slice,
                 sensor: SensorConfig) -> NDArray[np.float64]:
    """:func:`block_albedo` of one tile of whole blocks (its rays (rows, columns, 3) given), before clipping."""
    b = blocks.block_pixels
    block_rows, block_columns = slice(rows.start // b, -(-rows.stop // b)), slice(columns.start // b,
                                                                                  -(-columns.stop // b))
    depth = np.where(blocks.finite[rows, columns], scan.depth[-1, rows, columns].astype(np.float64), np.nan)
    amplitude = scan.amplitude[:, rows, columns].astype(np.float64).mean(0)
    normals = blocks.normals[block_rows, block_columns]
    cos_i = np.abs(np.einsum("hwni,hwi->hwn", np.nan_to_num(to_blocks(rays, b)), normals))
    ratio = to_blocks(amplitude * depth**2, b) / (sensor.gamma_r_v2 * np.maximum(cos_i, 0.1))
    return nanmedian_last(np.where(blocks.keep[block_rows, block_columns], ratio, np.nan))  # NaN: no inliers


def partner_albedo(blocks: FacingBlocks, measured: NDArray, components: NDArray) -> NDArray[np.float64]:
    """The albedo per block (Hb*Wb,) that weighs each partner's multipath in a correction model's inputs: its
    connected surface's (``components``, :func:`surface_labels`) :func:`surface_albedo` of the ``measured``
    albedos (:func:`block_albedo`), picked by the blocks' white coupling."""
    white = np.bincount(blocks.index[blocks.pairs.a], blocks.pairs.kappa(1.0), minlength=blocks.usable.size)
    return surface_albedo(measured, components, white)


def surface_albedo(albedo: NDArray, components: NDArray, coupling: NDArray) -> NDArray[np.float64]:
    """One albedo per connected surface (Hb*Wb,): the median over its blocks with the least ``coupling``
    (Hb*Wb,).

    Multipath adds light (Gamma = Gamma_D |1 + ratio|), most near an edge, so a block's own amplitude
    overstates its albedo just where the partners that matter lie; the surface's far blocks do not.
    Blocks outside any surface keep their own estimate.
    """
    out = albedo.copy()
    for label in np.unique(components[components >= 0]):
        members = np.flatnonzero(components == label)
        far = members[coupling[members] <= np.quantile(coupling[members], ANCHOR_SHARE)]
        out[members] = np.median(albedo[far])
    return out


class BlockPhasors:
    """The multipath phasor per block at unit footprint of the block ``pairs`` (A, B indices, kappa at
    1 m^2, distance [m]), for any albedos: the pairs' phases are worked out once.

    S_f = rho_A sum_B rho_B kappa_B e^{j 4 pi f r_AB / c} with kappa_B at A_fp = 1 m^2: the ratio
    Gamma_M / Gamma_D of the two-path model is A_fp S_f, and the white kappa sum K caps it like the
    renderer does (at A_fp K > 1 the multipath is scaled by 1 / (A_fp K)).
    """

    def __init__(self, blocks: FacingBlocks, frequencies_hz: tuple[float, ...], speed_of_light_m_per_s: float,
                 pairs: tuple[NDArray, NDArray, NDArray, NDArray]):
        self.block_count = blocks.usable.size
        self.block_a, self.block_b, self.kappa, distance_m = pairs
        freqs = np.asarray(frequencies_hz, dtype=np.float64)
        phase = 4 * np.pi * distance_m[:, None] * freqs[None, :] / speed_of_light_m_per_s
        self.cos, self.sin = np.cos(phase), np.sin(phase)

    def __call__(self, albedo: NDArray) -> NDArray[np.complex128]:
        """S_f per block (Hb*Wb, F) for the albedos per block ``albedo`` (Hb*Wb,)."""
        weight = self.kappa * albedo[self.block_a] * albedo[self.block_b]
        phasor = np.zeros((self.block_count, self.cos.shape[1]), dtype=np.complex128)
        for k in range(self.cos.shape[1]):
            phasor[:, k] = (np.bincount(self.block_a, weight * self.cos[:, k], minlength=self.block_count)
                            + 1j * np.bincount(self.block_a, weight * self.sin[:, k], minlength=self.block_count))
        return phasor


def _pixel_phasors(blocks: FacingBlocks, unit_phasor: NDArray, unit_kappa: NDArray,
                   coordinates: tuple[NDArray, NDArray]) -> tuple[NDArray[np.complex128], NDArray[np.float64]]:
    """Unit-footprint phasors (n, F) and white kappa (n,) at pixel coordinates, from the block values.

    kappa is interpolated as a coupling (:meth:`FacingBlocks.coupling_to_pixels`: 1 / sqrt(kappa) is linear in
    the distance from an edge), the phasor as kappa times its (smooth) ratio to kappa.
    """
    has = unit_kappa > 0
    kappa = blocks.coupling_to_pixels(unit_kappa, coordinates)
    ratio = np.where(has[:, None], unit_phasor / np.where(has, unit_kappa, 1.0)[:, None], 0.0)
    phasor = np.stack([blocks.to_pixels(ratio[:, k].real, coordinates) + 1j * blocks.to_pixels(ratio[:, k].imag,
                                                                                               coordinates)
                       for k in range(ratio.shape[1])], axis=1)
    return phasor * kappa[:, None], kappa


def surface_labels(blocks: FacingBlocks) -> tuple[NDArray[np.intp], NDArray[np.intp]]:
    """Connected surfaces of the blocks, and the flat surfaces among them: two labels (Hb*Wb,), -1 where none.

    Neighbouring blocks join when their normals agree to ``NEIGHBOUR_ANGLE_DEG`` and each centre lies on
    the other's plane to three times the fits' noise plus a fifth of their distance (a depth step is
    another surface). Within a surface, blocks that bend from its mean normal by more than
    ``SURFACE_ANGLE_DEG`` are dropped, and surfaces of fewer than ``MIN_SURFACE_BLOCKS`` blocks are dropped.
    """
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    hb, wb = blocks.usable.shape
    flat = np.arange(hb * wb).reshape(hb, wb)
    normals, centres = blocks.normals.reshape(-1, 3), blocks.centres.reshape(-1, 3)
    usable, rms = blocks.usable.ravel(), blocks.rms_m.ravel()
    edges = []
    for a, b in ((flat[:, :-1], flat[:, 1:]), (flat[:-1, :], flat[1:, :])):
        a, b = a.ravel(), b.ravel()
        offset = centres[b] - centres[a]
        gap = np.linalg.norm(offset, axis=1)
        tolerance = 3 * (rms[a] + rms[b]) + 0.2 * gap
        agree = (usable[a] & usable[b]
                 & (np.einsum("ij,ij->i", normals[a], normals[b]) > np.cos(np.deg2rad(NEIGHBOUR_ANGLE_DEG)))
                 & (np.abs(np.einsum("ij,ij->i", normals[a], offset)) <= tolerance)
                 & (np.abs(np.einsum("ij,ij->i", normals[b], offset)) <= tolerance))
        edges.append((a[agree], b[agree]))
    rows = np.concatenate([e[0] for e in edges])
    cols = np.concatenate([e[1] for e in edges])
    graph = coo_matrix((np.ones(rows.size), (rows, cols)), shape=(hb * wb, hb * wb))
    _, labels = connected_components(graph, directed=False)
    labels = np.where(usable, labels, -1)
    components = labels.copy()
    # Mean normal per surface; blocks bending away from it are left out, then small surfaces.
    valid = labels >= 0
    sums = np.zeros((labels.max() + 2, 3))
    np.add.at(sums, labels[valid], normals[valid])
    mean = sums / np.maximum(np.linalg.norm(sums, axis=1, keepdims=True), 1e-12)
    bends = np.einsum("ij,ij->i", normals, mean[labels]) < np.cos(np.deg2rad(SURFACE_ANGLE_DEG))
    labels = np.where(valid & ~bends, labels, -1)
    counts = np.bincount(labels[labels >= 0], minlength=labels.max() + 2)
    return components, np.where((labels >= 0) & (counts[labels] >= MIN_SURFACE_BLOCKS), labels, -1)


def _fit_pixels(blocks: FacingBlocks, labels: NDArray, unit_kappa: NDArray, valid: NDArray, max_pixels: int
                ) -> NDArray[np.intp]:
    """Flat indices of the pixels the fit uses: valid inliers of surfaces that have a facing partner.

    A surface without any facing partner cannot tell the footprint and is left out; at most
    ``max_pixels``, on a regular stride.
    """
    h, w = blocks.shape
    b = blocks.block_pixels
    hb, wb = blocks.usable.shape
    informative = np.unique(labels[(unit_kappa > 0) & (labels >= 0)])
    if informative.size == 0:
        return np.zeros(0, dtype=np.intp)
    surface_blocks = np.isin(labels, informative).reshape(hb, wb)
    inlier = blocks.keep & surface_blocks[..., None]
    # Back from (Hb, Wb, b*b) to pixels (H, W): the inverse of geometry.to_blocks.
    grid = inlier.reshape(hb, wb, b, b).swapaxes(1, 2).reshape(hb * b, wb * b)[:h, :w]
    return evenly_chosen(grid & np.asarray(valid, dtype=bool).reshape(h, w) & blocks.finite, max_pixels)


def evenly_chosen(mask: NDArray[np.bool_], count: int) -> NDArray[np.intp]:
    """Flat indices of the True pixels of ``mask`` (H, W), or of ``count`` of them on a regular stride.

    The same indices as ``np.flatnonzero(mask)[np.linspace(0, n - 1, count).astype(np.intp)]``, found row
    by row: the indices of every True pixel (8 bytes each, 128 MiB at 4000 x 4000) never exist at once.
    """
    per_row = np.count_nonzero(mask, axis=1)
    total = int(per_row.sum())
    if total <= count:
        return np.flatnonzero(mask)
    ranks = np.linspace(0, total - 1, count).astype(np.intp)
    row_starts = np.concatenate([[0], np.cumsum(per_row)])
    rows = np.searchsorted(row_starts, ranks, side="right") - 1
    chosen = np.empty(count, dtype=np.intp)
    width = mask.shape[1]
    found, first = np.unique(rows, return_index=True)  # ranks ascend, so each row's ranks are one run
    for row, start, stop in zip(found, first, [*first[1:], count], strict=True):
        chosen[start:stop] = row * width + np.flatnonzero(mask[row])[ranks[start:stop] - row_starts[row]]
    return chosen


class _Problem:
    """Weighted least squares for planes per surface and one footprint A shared by all pixels and frequencies.

    Rows are (pixel, frequency); ``depth``, ``sigma`` (n, F) [m], ``phasor`` (n, F) the unit-footprint
    multipath phasor, ``kappa`` (n,) the white coupling at unit footprint, ``rays`` (n, 3), ``surface`` (n,)
    labels, and ``reference`` (n,) [m] in place of planes where given.
    """

    def __init__(self, depth: NDArray, sigma: NDArray, phasor: NDArray, kappa: NDArray, metres_per_rad: NDArray,
                 relative_amplitude: NDArray, rays: NDArray, surface: NDArray, reference: NDArray | None):
        self.depth, self.sigma, self.phasor, self.kappa = depth, sigma, phasor, kappa
        # The bias model in real arithmetic (complex NumPy is several times slower): the phasor's parts.
        self.phasor_re, self.phasor_im = np.ascontiguousarray(phasor.real), np.ascontiguousarray(phasor.imag)
        self.inverse_variance = sigma**-2.0
        self.log_amplitude = np.log(np.maximum(relative_amplitude, 1e-12))
        self.sigma_log = sigma / metres_per_rad
        self.metres_per_rad, self.rays, self.reference = metres_per_rad, rays, reference
        self.labels, self.surface = np.unique(surface, return_inverse=True)
        self.surfaces = int(self.surface.max()) + 1 if surface.size else 0
        # Sums per surface as one matrix product: (surfaces, n) one-hot rows.
        self.members = (self.surface[None, :] == np.arange(self.surfaces)[:, None]).astype(np.float64)
        self.anchor = self._anchor_rows()
        self.ray_outer = np.einsum("ni,nj->nij", rays, rays).reshape(-1, 9)  # the planes' normal equations

    def bias(self, area: float, amplitude: bool = True) -> tuple[NDArray, NDArray, NDArray | None, NDArray | None]:
        """Predicted depth bias (n, F) [m] at footprint ``area``, its derivative in the footprint, the
        amplitude gain |1 + ratio| (n, F) and the derivative of its logarithm (those two only with
        ``amplitude``, else None)."""
        # ratio = area S / max(area K, 1); with 1 + ratio = x + j y, the derivative of the phase in the
        # footprint is Im(S' / (1 + ratio)) and that of log|1 + ratio| its real part (S' = S / max(area K, 1)).
        coupling = abs(area) * self.kappa
        scale = (1.0 / np.maximum(coupling, 1.0))[:, None]
        s_re, s_im = self.phasor_re * scale, self.phasor_im * scale
        x, y = 1.0 + area * s_re, area * s_im
        bias = np.arctan2(y, x) * self.metres_per_rad
        norm2 = x * x + y * y
        capped = (coupling > 1.0)[:, None] | (norm2 < 1e-18)
        inverse = np.where(capped, 0.0, 1.0 / np.where(capped, 1.0, norm2)) if capped.any() else 1.0 / norm2
        slope = (s_im * x - s_re * y) * inverse * self.metres_per_rad
        if not amplitude:
            return bias, slope, None, None
        gain = np.where(capped, 1.0, np.sqrt(norm2))
        return bias, slope, gain, (s_re * x + s_im * y) * inverse

    def solve(self, method: str, with_amplitude: bool = True, start_m2: float = 0.0,
              tolerance: float = CONVERGED_STEP) -> FootprintEstimate:
        """The footprint from the depth residuals (over the fitted planes or against the reference depth) and,
        over the planes, from the amplitude.

        Each estimate's statistical uncertainty is combined with a systematic one, a share of the estimate
        (``DEPTH_SYSTEMATIC_SHARE``, ``AMPLITUDE_SYSTEMATIC_SHARE``): their spread over rendered scenes the
        scan's geometry describes only in part (partners beyond the field of view, 3 cm blocks).
        ``with_amplitude``: fit the amplitude too, from the depth's estimate (:meth:`_with_amplitude`).
        ``start_m2``: the footprint the depth fit starts from (an earlier estimate saves iterations; without
        one, the best of a coarse grid, :meth:`_best_start`). ``tolerance``: the relative step of A that ends
        the depth's fit.
        """
        problem = self if self.reference is not None else self.anchored
        start_m2 = start_m2 or problem._best_start()
        found = problem._solve(method, use_depth=True, use_amplitude=False, start_m2=start_m2, tolerance=tolerance)
        if not np.isfinite(found.area_m2) or abs(found.area_m2) > MAX_PLAUSIBLE_M2:
            # No receiver sees a square metre: such a number comes from a few spurious facing blocks.
            return FootprintEstimate(float("nan"), float("inf"), found.pixels, found.surfaces, method)
        depth = replace(found, sigma_m2=float(np.hypot(found.sigma_m2, DEPTH_SYSTEMATIC_SHARE * found.area_m2)))
        if not with_amplitude or self.reference is not None:
            return depth
        return problem._with_amplitude(depth)

    def _anchor_and_fit_rows(self) -> tuple[NDArray[np.bool_], NDArray[np.bool_]]:
        """The rows that fix the planes (none against a reference) and the rows A is fitted to."""
        anchor = self.anchor if self.reference is None else np.zeros(self.depth.shape[0], dtype=bool)
        return anchor, (self.kappa > 0) & ~anchor

    def _surface_range(self, bias: NDArray, anchor: NDArray) -> tuple[NDArray, NDArray | None]:
        """The range (n,) each row's depth is measured against, and the planes (None against a reference)."""
        if self.reference is not None:
            return self.reference, None
        return self._plane_range(bias, anchor)

    def _trusted(self, area: float, surface_range: NDArray) -> NDArray[np.bool_]:
        """Rows (n,) the fit at footprint ``area`` uses: coupling within the model's reach, and a surface
        whose plane could be fitted (a surface with too few anchors has no range)."""
        return (abs(area) * self.kappa <= MAX_FIT_COUPLING) & np.isfinite(surface_range)

    def _best_start(self) -> float:
        """The footprint of :data:`START_GRID_M2` whose depth residuals over the fit rows are smallest (median
        of the standardized residuals, each footprint over the rows it trusts).

        Where the multipath is strong the residuals are not convex in A: the planes, anchored on pixels that
        are themselves biased, take up part of the bias, and a fit started from A = 0 can settle on a second,
        smaller minimum (even a negative footprint) while the true one lies near 0.1 m^2.
        """
        anchor, fit_rows = self._anchor_and_fit_rows()
        best, best_spread = 0.0, np.inf
        for area in START_GRID_M2:
            bias = self.bias(area, amplitude=False)[0]
            surface_range = self._surface_range(bias, anchor)[0]
            rows = fit_rows & self._trusted(area, surface_range)
            if rows.sum() < MIN_INFORMATIVE_PIXELS:
                continue
            z = (self.depth[rows] - surface_range[rows, None] - bias[rows]) / self.sigma[rows]
            spread = float(np.median(np.abs(z)))
            if spread < best_spread:
                best, best_spread = float(area), spread
        return best

    def _with_amplitude(self, depth: FootprintEstimate) -> FootprintEstimate:
        """The depth's estimate joined with the amplitude's: their mean in log A, each weighted by its inverse
        relative variance; not significant where the two differ by more than ``AMPLITUDE_AGREEMENT``.

        Multipath adds light as well as range. A scan whose depth residuals suggest a footprint its
        amplitude does not show (a dark corner, where the predicted bias is tiny and any residual the
        planes leave looks like multipath) is not described by the model. Where they agree, the amplitude
        weighs the more: strong multipath bends each surface near its partners, and the planes the depth is
        measured against take up part of the bias, while the amplitude's gain |1 + ratio| is measured
        against each surface's own albedo (one per surface, eliminated).
        """
        light = self._solve(depth.method, use_depth=False, use_amplitude=True, start_m2=depth.area_m2,
                            tolerance=AMPLITUDE_STEP)
        if not (depth.area_m2 > 0 and np.isfinite(light.area_m2) and light.area_m2 > 0
                and 1 / AMPLITUDE_AGREEMENT <= light.area_m2 / depth.area_m2 <= AMPLITUDE_AGREEMENT):
            # The scan is not what the model describes: not significant.
            return replace(depth, sigma_m2=max(depth.sigma_m2, abs(depth.area_m2)))
        systematic = np.hypot(AMPLITUDE_SYSTEMATIC_SHARE * light.area_m2,
                              AMPLITUDE_SYSTEMATIC_LOG / max(self._light_lever(light.area_m2), 1e-300))
        light = replace(light, sigma_m2=float(np.hypot(light.sigma_m2, systematic)))
        weights = np.array([(e.area_m2 / e.sigma_m2) ** 2 for e in (depth, light)])
        log_area = np.log([depth.area_m2, light.area_m2]) @ weights / weights.sum()
        area = float(np.exp(log_area))
        return replace(depth, area_m2=area, sigma_m2=float(area * weights.sum() ** -0.5))

    def _light_lever(self, area: float) -> float:
        """Inverse-variance weighted rms of d log|1 + ratio| / dA [1 / m^2] over the rows the amplitude fit
        uses, less its mean per surface (each surface's albedo is eliminated)."""
        bias, _, _, gain_slope = self.bias(area)
        trusted = self._trusted(area, self._plane_range(bias, self.anchor)[0])[:, None]
        weight = np.where(trusted, 1.0 / self.sigma_log**2, 0.0)
        centred = self._less_surface_mean(gain_slope, weight)
        return float(np.sqrt((weight * centred**2).sum() / max(weight.sum(), 1e-300)))

    def _less_surface_mean(self, values: NDArray, weight: NDArray) -> NDArray:
        """``values`` (n, F) less their ``weight``-ed mean over each surface's rows (its albedo eliminated)."""
        total = np.maximum(np.bincount(self.surface, weight.sum(1), minlength=self.surfaces), 1e-300)
        mean = np.bincount(self.surface, (weight * values).sum(1), minlength=self.surfaces) / total
        return values - mean[self.surface][:, None]

    def _solve(self, method: str, use_depth: bool, use_amplitude: bool, start_m2: float = 0.0,
               tolerance: float = CONVERGED_STEP) -> FootprintEstimate:
        n = self.depth.shape[0]
        informative = int((self.kappa > 0).sum())
        if n < 10 or informative == 0:
            return FootprintEstimate(float("nan"), float("inf"), informative, self.surfaces, method)
        anchor, fit_rows = self._anchor_and_fit_rows()
        area = start_m2
        robust_depth, robust_amplitude = np.ones_like(self.depth), np.ones_like(self.depth)
        spread, information = 1.0, 0.0
        # Before A is near, the multipath itself looks like an outlier: plain least squares first, unless the
        # fit starts from an earlier estimate.
        plain = PLAIN_ITERATIONS if start_m2 == 0 else 0
        for iteration in range(MAX_ITERATIONS):
            robust = iteration >= plain
            bias, slope, gain, gain_slope = self.bias(area, amplitude=use_amplitude)
            surface_range, planes = self._surface_range(bias, anchor)
            if planes is not None and use_depth:
                # The planes move with A (their anchors' predicted bias is taken off): the residual's
                # derivative holds that motion too, or the fit settles where the residuals are not least.
                step_m2 = PLANE_STEP * max(abs(area), 1e-3)
                moved = self._plane_range(bias + step_m2 * slope, anchor)[0]
                slope = slope + ((moved - surface_range) / step_m2)[:, None]
            trusted = self._trusted(area, surface_range)[:, None]
            residual = np.where(trusted, self.depth - np.nan_to_num(surface_range)[:, None] - bias, 0.0)
            numerator = information = 0.0
            if use_depth:
                z = residual / self.sigma
                spread = 1.4826 * float(np.median(np.abs(z[fit_rows]))) or 1.0
                if robust:
                    robust_depth = _huber(z, spread)
                weight = np.where(trusted & fit_rows[:, None], robust_depth * self.inverse_variance, 0.0)
                numerator = float((weight * slope * residual).sum())
                information = float((weight * slope**2).sum())
            if planes is not None and use_amplitude:
                step_terms = self._amplitude_terms(planes, surface_range, gain, gain_slope, trusted,
                                                   robust_amplitude, robust)
                numerator += step_terms[0]
                information += step_terms[1]
                robust_amplitude, spread = step_terms[2], step_terms[3]
            if information <= 0:  # nothing left to measure A on (every row capped or outside the fit)
                return FootprintEstimate(float("nan"), float("inf"), informative, self.surfaces, method)
            step = numerator / information
            area += step
            if robust and abs(step) <= tolerance * max(abs(area), 1e-4):
                break
        variance = 1.0 / information
        if planes is not None and use_depth:
            variance += self._plane_noise(weight * slope, surface_range, bias, anchor) / information**2
        return FootprintEstimate(float(area), float(spread * np.sqrt(variance)), informative, self.surfaces, method)

    def _plane_noise(self, weighted_slope: NDArray, surface_range: NDArray, bias: NDArray, anchor: NDArray) -> float:
        """The variance the anchors' noise adds to the fit's numerator through the planes, in units of the
        residuals' variance: sum over surfaces of h_s' M_s^-1 h_s.

        A plane u (u . ray = 1 / range) fitted to the anchors with their inverse variances has covariance
        M_s^-1, its normal matrix; a fit row's range then moves by -range^2 ray . du, and the numerator
        sum w g r by h_s . du with h_s the sum over the surface's fit rows of w g range^2 ray. On a narrow
        surface, whose plane rests on a strip of anchors, this term outweighs the fit rows' own noise.
        """
        pull = np.nan_to_num(weighted_slope.sum(1) * surface_range**2)[:, None] * self.rays
        pulls = self.members @ pull
        matrices = self._plane_system(bias, anchor)[0]
        return float(np.einsum("si,si->", pulls, np.linalg.solve(matrices, pulls[..., None])[..., 0]))

    def _amplitude_terms(self, planes: NDArray, surface_range: NDArray, gain: NDArray, gain_slope: NDArray,
                         trusted: NDArray, weights: NDArray, robust: bool) -> tuple[float, float, NDArray, float]:
        """Gauss-Newton sums (numerator, information) of the amplitude rows, their Huber weights (``weights``
        as they were where not ``robust`` yet) and spread."""
        # Lambertian direct light: amplitude / Gamma_R = rho cos_i / t^2 with cos_i = 1 / (t |u|).
        with np.errstate(divide="ignore", invalid="ignore"):
            log_direct = -np.log(surface_range**3 * np.linalg.norm(planes[self.surface], axis=1))
        residual = np.where(trusted, self.log_amplitude - np.nan_to_num(log_direct)[:, None] - np.log(gain), 0.0)
        weight = np.where(trusted, weights / self.sigma_log**2, 0.0)
        # Eliminate log rho per surface: weighted means.
        residual = self._less_surface_mean(residual, weight)
        slope = self._less_surface_mean(gain_slope, weight)
        z = residual / self.sigma_log
        spread = 1.4826 * float(np.median(np.abs(z))) or 1.0
        if robust:  # the weights of this step's residuals, as the depth's are
            weights = _huber(z, spread)
            weight = np.where(trusted, weights / self.sigma_log**2, 0.0)
        return float((weight * slope * residual).sum()), float((weight * slope**2).sum()), weights, spread

    @functools.cached_property
    def anchored(self) -> _Problem:
        """This problem without the surfaces whose anchors cannot fix a plane: too few, or along a line (built
        once: the fit and the second round's partner planes both rest on it).

        A strip along an edge that the multipath bent away from its surface has pixels close to their
        partners only: it has no plane to measure the bias against. A plane its anchors leave free to turn
        could put any bias on its other pixels.
        """
        anchor = self._anchor_rows()
        anchors = np.bincount(self.surface, anchor, minlength=self.surfaces)
        fixed = np.linalg.cond(self._plane_system(np.zeros_like(self.depth), anchor)[0]) < MAX_PLANE_CONDITION
        keep = ((anchors >= MIN_ANCHOR_PIXELS) & fixed)[self.surface]
        kept = _Problem(self.depth[keep], self.sigma[keep], self.phasor[keep], self.kappa[keep], self.metres_per_rad,
                        np.exp(self.log_amplitude[keep]), self.rays[keep], self.surface[keep], None)
        kept.anchor = anchor[keep]
        kept.labels = self.labels[np.unique(self.surface[keep])]
        return kept

    def anchored_planes(self, area: float) -> dict[int, NDArray]:
        """The planes u . x = 1 of the surfaces whose anchors fix one, fitted to the anchors less the bias
        predicted at footprint ``area``, by surface label."""
        kept = self.anchored
        planes = kept._plane_range(kept.bias(area, amplitude=False)[0], kept.anchor)[1]
        return {int(label): planes[k] for k, label in enumerate(kept.labels)}

    def _anchor_rows(self) -> NDArray[np.bool_]:
        """Pixels that fix the surfaces' planes: the share ``ANCHOR_SHARE`` of all with the least coupling."""
        if self.kappa.size == 0:
            return np.zeros(0, dtype=bool)
        return self.kappa <= np.quantile(self.kappa, ANCHOR_SHARE)

    def _plane_range(self, bias: NDArray, anchor: NDArray) -> tuple[NDArray, NDArray]:
        """Range (n,) [m] of each pixel's surface plane, fitted to the anchors' depth less the predicted bias.

        The plane u . ray = 1 / range is a weighted least-squares fit per surface of the inverse-variance
        mean depth over the frequencies, each anchor weighted by its range noise (d(1/r) = dr / r^2).
        """
        matrices, vectors = self._plane_system(bias, anchor)
        planes = np.linalg.solve(matrices, vectors[..., None])[..., 0]
        with np.errstate(divide="ignore", invalid="ignore"):
            inverse_range = np.einsum("ni,ni->n", self.rays, planes[self.surface])
            return np.where(inverse_range > 0, 1.0 / inverse_range, np.nan), planes

    def _plane_system(self, bias: NDArray, anchor: NDArray) -> tuple[NDArray, NDArray]:
        """Normal equations (matrices (S, 3, 3), vectors (S, 3)) of the surfaces' planes u . ray = 1 / range,
        fitted to the anchors' inverse-variance mean depth over the frequencies less the predicted bias, each
        anchor weighted by the inverse variance of 1 / range (d(1/r) = dr / r^2)."""
        total = self.inverse_variance.sum(1)
        depth = ((self.depth - bias) * self.inverse_variance).sum(1) / total
        weighted_members = self.members * np.where(anchor, depth**4 * total, 0.0)
        matrices = (weighted_members @ self.ray_outer).reshape(-1, 3, 3) + 1e-9 * np.eye(3)
        return matrices, (weighted_members / depth) @ self.rays


def _huber(z: NDArray, spread: float) -> NDArray:
    """Huber weights of standardized residuals, zero beyond six robust spreads."""
    return np.where(np.abs(z) > 6 * spread, 0.0, np.minimum(1.0, HUBER_K * spread / np.maximum(np.abs(z), 1e-12)))


def pool_estimates(estimates: list[FootprintEstimate]) -> FootprintEstimate:
    """One footprint from several scans' estimates: their inverse-variance mean (scans without one add nothing)."""
    usable = [e for e in estimates if np.isfinite(e.area_m2) and np.isfinite(e.sigma_m2) and e.sigma_m2 > 0]
    methods = sorted({e.method for e in estimates}) or ["planes"]
    if not usable:
        return FootprintEstimate(float("nan"), float("inf"), sum(e.pixels for e in estimates),
                                 sum(e.surfaces for e in estimates), "+".join(methods), len(estimates))
    weights = np.array([e.sigma_m2**-2 for e in usable])
    area = float(np.sum(weights * [e.area_m2 for e in usable]) / weights.sum())
    return FootprintEstimate(area, float(weights.sum() ** -0.5), sum(e.pixels for e in estimates),
                             sum(e.surfaces for e in estimates), "+".join(methods), len(estimates))
