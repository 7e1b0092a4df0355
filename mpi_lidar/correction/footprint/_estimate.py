"""The receiver footprint a scan measures on its own facing surfaces: :func:`estimate_footprint`.

On two surfaces that face each other the raw depth drifts away from the surfaces' planes towards their shared
edge, in proportion to A_fp and with the shape the geometry predicts (F5, F6), while far from the edge the
surfaces are unbiased. The fit (:mod:`._fit`) measures A on the pixels of the flat surfaces that have a facing
partner, in rounds: a first on every third pixel gives the second, on every pixel, its start, its albedos and its
partner planes (strong multipath bends each surface near its partners, and the planes through its blocks meet
at too sharp an angle); a third follows where the second's estimate moves the albedos by more than
``ALBEDO_STEP``.
"""

from __future__ import annotations

import dataclasses

import numpy as np
from numpy.typing import NDArray

from mpi_lidar.config import SensorConfig
from mpi_lidar.correction.footprint._albedo import block_albedo, light_free_albedo, white_albedo
from mpi_lidar.correction.footprint._coupling import PixelCoupling, PlaneCoupling
from mpi_lidar.correction.footprint._fit import FootprintFit
from mpi_lidar.correction.footprint._result import NOTHING_MEASURED, EstimateMethod, FootprintEstimate
from mpi_lidar.correction.footprint._surfaces import SurfaceLabels, pair_coupling, surface_labels
from mpi_lidar.physics.noise import NoiseModel
from mpi_lidar.scans.geometry import FacingBlocks
from mpi_lidar.scans.scan import Scan

# Pixels the fit uses at most: a subsample on a regular stride keeps the cost a small share of correction
# (the systematic uncertainty dwarfs the statistical one long before).
MAX_FIT_PIXELS = 12_000
# The first round sets only the second's start, albedos and partner planes: every third pixel, and a 1 % step
# of A ends it.
FIRST_ROUND_STRIDE = 3
EARLY_ROUND_STEP = 1e-2
# Rounds of the fit after the first at most, another only where the last estimate moves the albedos by more
# than this share.
ALBEDO_ROUNDS = 2
ALBEDO_STEP = 0.02
# Rounds that refit the planes unbent by the multipath with the coupling of the planes the round before found.
UNBENDING_ROUNDS = 2
# Depth noise below this [m] is taken as this.
MIN_DEPTH_NOISE_M = 1e-5


def estimate_footprint(scan: Scan, blocks: FacingBlocks, valid: NDArray, sensor: SensorConfig, *,
                       reference: bool = False, max_pixels: int = MAX_FIT_PIXELS,
                       measured_albedo: NDArray | None = None, surfaces: SurfaceLabels | None = None,
                       noise: NoiseModel | None = None, white_partners: bool = False) -> FootprintEstimate:
    """The receiver footprint A_fp [m^2] that best explains the scan's depth near facing surfaces.

    Parameters
    ----------
    scan : Scan
        The scan.
    blocks : FacingBlocks
        Its :func:`mpi_lidar.scans.geometry.facing_blocks` (from its highest-frequency depth).
    valid : NDArray
        Bool (H*W,): the pixels whose measurements can be trusted.
    sensor : SensorConfig
        The sensor (noise model, Gamma_R, c).
    reference : bool
        Measure the depth against the scan's reference depth (it must have one) instead of fitted planes; the
        amplitude is then not used.
    max_pixels : int
        Pixels the fit uses at most, on a regular stride.
    measured_albedo : NDArray | None
        The scan's :func:`block_albedo` (Hb*Wb,), where the caller has it already. [1]
    surfaces : SurfaceLabels | None
        The blocks' :func:`surface_labels`, where the caller has them already.
    noise : NoiseModel | None
        The scan's noise model, which weighs each pixel's depths (None: the sensor's).
    white_partners : bool
        Take every surface as white instead of reading its albedo from the amplitude, for a scan whose amplitude
        unit is not known (an albedo in the wrong unit is off by the unit's factor, and the estimate by its
        inverse). The estimate is then the footprint times the albedos of the surfaces the light returns from,
        A_fp rho_A rho_B ((F5) of :mod:`._coupling`): the product the bias rests on, so the bias of white
        surfaces at it is the scan's own. ``measured_albedo`` is not read; the amplitude's fit, which measures
        each surface against its own mean, needs no unit.

    Returns
    -------
    FootprintEstimate
        The estimate; :data:`NOTHING_MEASURED` where nothing faces.
    """
    if blocks.pairs.a.size == 0:
        return NOTHING_MEASURED
    if surfaces is None:
        surfaces = surface_labels(blocks)
    # Against a reference every surface, flat or not, measures the bias; the partners are the flat surfaces.
    measured_surfaces = np.where(blocks.usable.ravel(), 0, -1) if reference else surfaces.flat
    fit_rows = FitRows(scan, blocks, surfaces, valid, sensor, noise, measured_surfaces, max_pixels, reference)
    if fit_rows.pixels.size == 0:
        return NOTHING_MEASURED
    method = EstimateMethod.REFERENCE if reference else EstimateMethod.PLANES
    if white_partners:
        measured_albedo = white_albedo(blocks)
    elif measured_albedo is None:
        measured_albedo = block_albedo(scan, blocks, sensor)
    rows = np.flatnonzero(fit_rows.usable)
    first_rows = rows[::FIRST_ROUND_STRIDE]
    first_coupling = fit_rows.coupling(first_rows)
    first_albedo = (measured_albedo if white_partners
                    else light_free_albedo(first_coupling.plane, measured_albedo, surfaces.components, 0.0))
    first_fit = fit_rows.fit(first_rows, first_coupling, first_albedo)
    first = first_fit.solve(method, with_amplitude=False, tolerance=EARLY_ROUND_STEP)
    if not (np.isfinite(first.area_m2) and first.area_m2 > 0):  # no multipath to correct for: one round on all
        found = fit_rows.fit(rows, fit_rows.coupling(rows), first_albedo).solve(method)
        return dataclasses.replace(found, white_surfaces=white_partners)
    # Strong multipath bends each surface near its partners, so the planes through its blocks meet at too
    # sharp an angle and predict too much coupling; the planes of the later rounds rest on the anchors less the
    # bias predicted at the first estimate.
    last_coupling = fit_rows.coupling(rows, None if reference else first_fit.fixed_planes(first.area_m2))
    if white_partners:  # no albedo to take the multipath's gain off
        found = fit_rows.fit(rows, last_coupling, first_albedo).solve(method, start_m2=first.area_m2)
        return dataclasses.replace(found, white_surfaces=True)
    # Multipath adds light, so the amplitude overstates the albedos (at strong multipath on the whole of a
    # surface near its partners): each round's albedos are the measured ones less the gain the multipath gives
    # at the estimate before it, and a round that moves them by more than ALBEDO_STEP is followed by another.
    area, albedo = first.area_m2, None
    for _ in range(ALBEDO_ROUNDS):
        without_gain = light_free_albedo(last_coupling.plane, measured_albedo, surfaces.components, area)
        if albedo is not None and _largest_change(albedo, without_gain) <= ALBEDO_STEP:
            break
        albedo = without_gain
        estimate = fit_rows.fit(rows, last_coupling, albedo).solve(method, start_m2=area)
        if not (np.isfinite(estimate.area_m2) and estimate.area_m2 > 0):
            break
        area = estimate.area_m2
    return estimate


class FitRows:
    """The pixels a footprint fit uses (:func:`_fit_pixels` of the surfaces ``measured_surfaces`` (Hb*Wb,)) and
    their measurements: depth and amplitude (n, F), the depth's noise under ``noise`` (None: the sensor's) and the
    rows whose every value is finite (``usable``); against the scan's reference depth where ``reference``.
    :meth:`coupling` and :meth:`fit` build a fit on some of the rows."""

    def __init__(self, scan: Scan, blocks: FacingBlocks, surfaces: SurfaceLabels, valid: NDArray,
                 sensor: SensorConfig, noise: NoiseModel | None, measured_surfaces: NDArray, max_pixels: int,
                 reference: bool = False):
        self.scan, self.blocks, self.surfaces, self.sensor = scan, blocks, surfaces, sensor
        self.pixels = _fit_pixels(blocks, measured_surfaces, pair_coupling(blocks), valid, max_pixels)
        ys, xs = np.divmod(self.pixels, blocks.shape[1])
        self.depth = scan.depth[:, ys, xs].astype(np.float64).T
        self.amplitude = scan.amplitude[:, ys, xs].astype(np.float64).T
        noise = noise or NoiseModel.for_sensor(sensor, scan.frequencies_hz)
        self.metres_per_rad = noise.metres_per_radian
        self.sigma = np.maximum(noise.depth_sigma_m(self.amplitude), MIN_DEPTH_NOISE_M)
        self.usable = np.isfinite(self.depth).all(1) & np.isfinite(self.sigma).all(1)
        self.reference_depth = None
        if reference:
            assert scan.reference_depth is not None, "a scan with a reference depth"
            self.reference_depth = scan.reference_depth.ravel()[self.pixels].astype(np.float64)

    def coupling(self, rows: NDArray, planes: dict[int, NDArray] | None = None) -> PixelCoupling:
        """The coupling of ``rows`` (their indices), the surfaces on ``planes`` (u by label) where given."""
        return PixelCoupling(PlaneCoupling(self.scan, self.blocks, self.surfaces, self.sensor, planes),
                             self.pixels[rows], self.depth[rows, -1])

    def fit(self, rows: NDArray, coupling: PixelCoupling, albedo: NDArray) -> FootprintFit:
        """The fit of ``rows`` with ``coupling`` (theirs) at the albedos per block ``albedo`` (Hb*Wb,)."""
        phasor, kappa = coupling(albedo)
        return FootprintFit(self.depth[rows], self.sigma[rows], phasor, kappa, self.metres_per_rad,
                            self.amplitude[rows] / self.sensor.gamma_r_v2, coupling.rays, coupling.surface,
                            None if self.reference_depth is None else self.reference_depth[rows])


def unbent_planes(scan: Scan, blocks: FacingBlocks, valid: NDArray, sensor: SensorConfig, area_m2: float, *,
                  surfaces: SurfaceLabels, measured_albedo: NDArray, white_surfaces: bool = False,
                  noise: NoiseModel | None = None, max_pixels: int = MAX_FIT_PIXELS) -> dict[int, NDArray]:
    """The planes (u [1/m] by flat-surface label, u . x = 1) of the surfaces whose depths the multipath at
    footprint ``area_m2`` [m^2] bent, for the coupling of the model's inputs.

    Multipath lengthens a surface's depths towards its partners, so the plane through its blocks turns towards
    them and puts the partners nearer than they are: on a 90-degree corner at 0.073 m^2 the boards' planes meet
    2.4 degrees too sharply and the coupling reads 1.28x the render's (1.53x at 0.16 m^2). A surface's plane fitted
    to its least-coupled pixels less the bias predicted at ``area_m2`` (:meth:`FootprintProblem.fixed_planes`)
    reads the coupling to 3 % there (8 % at 0.16 m^2); it replaces the one through the blocks where it explains the
    surface's depths less that bias better (:meth:`FootprintProblem.unbent_planes`): a small surface whose few
    anchors lie near its partners keeps its blocks' plane. The fit's rows are every third of those
    :func:`estimate_footprint` uses; the albedos: ``measured_albedo`` (:func:`block_albedo`) less the multipath's
    gain at ``area_m2``, or as given where ``white_surfaces``. Nothing faces, or a footprint of zero: no planes.
    """
    if blocks.pairs.a.size == 0 or not area_m2 > 0:
        return {}
    fit_rows = FitRows(scan, blocks, surfaces, valid, sensor, noise, surfaces.flat, max_pixels)
    rows = np.flatnonzero(fit_rows.usable)[::FIRST_ROUND_STRIDE]
    if rows.size == 0:
        return {}
    coupling = fit_rows.coupling(rows)
    albedo = (measured_albedo if white_surfaces
              else light_free_albedo(coupling.plane, measured_albedo, surfaces.components, area_m2))
    through_blocks = {label: plane.vector for label, plane in coupling.plane.partners.planes.items()}
    # The anchors' bias is predicted with the coupling of the planes before: first the blocks' (too large), then
    # the planes each round found (a third round moves it by about 2 %).
    fit = fit_rows.fit(rows, coupling, albedo)
    for _ in range(UNBENDING_ROUNDS):
        fit = fit_rows.fit(rows, fit_rows.coupling(rows, fit.fixed_planes(area_m2)), albedo)
    return fit.unbent_planes(area_m2, through_blocks)


def _largest_change(before: NDArray, after: NDArray) -> float:
    """The largest relative change from ``before`` to ``after`` where ``before`` is positive."""
    positive = before > 0
    return float(np.max(np.abs(after[positive] / before[positive] - 1.0), initial=0.0))


def _fit_pixels(blocks: FacingBlocks, labels: NDArray, unit_coupling: NDArray, valid: NDArray, max_pixels: int
                ) -> NDArray[np.intp]:
    """Flat indices of the pixels the fit uses: valid inliers of the surfaces ``labels`` (Hb*Wb,) that have a
    facing partner (``unit_coupling`` (Hb*Wb,) above zero on one of their blocks).

    A surface without any facing partner cannot tell the footprint and is left out; at most ``max_pixels``, on a
    regular stride.
    """
    h, w = blocks.shape
    b = blocks.block_pixels
    hb, wb = blocks.usable.shape
    informative = np.unique(labels[(unit_coupling > 0) & (labels >= 0)])
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
