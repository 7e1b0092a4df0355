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
    pixels = _fit_pixels(blocks, measured_surfaces, pair_coupling(blocks), valid, max_pixels)
    if pixels.size == 0:
        return NOTHING_MEASURED
    ys, xs = np.divmod(pixels, blocks.shape[1])
    depth = scan.depth[:, ys, xs].astype(np.float64).T
    amplitude = scan.amplitude[:, ys, xs].astype(np.float64).T
    noise = noise or NoiseModel.for_sensor(sensor, scan.frequencies_hz)
    metres_per_rad = noise.metres_per_radian
    sigma = np.maximum(noise.depth_sigma_m(amplitude), MIN_DEPTH_NOISE_M)
    usable = np.isfinite(depth).all(1) & np.isfinite(sigma).all(1)
    reference_depth = None
    if reference:
        assert scan.reference_depth is not None, "a scan with a reference depth"
        reference_depth = scan.reference_depth.ravel()[pixels].astype(np.float64)
    method = EstimateMethod.REFERENCE if reference else EstimateMethod.PLANES

    def pixel_coupling(rows: NDArray, planes: dict[int, NDArray] | None = None) -> PixelCoupling:
        return PixelCoupling(PlaneCoupling(scan, blocks, surfaces, sensor, planes), pixels[rows], depth[rows, -1])

    def fit(rows: NDArray, coupling: PixelCoupling, albedo: NDArray) -> FootprintFit:
        phasor, kappa = coupling(albedo)
        return FootprintFit(depth[rows], sigma[rows], phasor, kappa, metres_per_rad,
                            amplitude[rows] / sensor.gamma_r_v2, coupling.rays, coupling.surface,
                            None if reference_depth is None else reference_depth[rows])

    if white_partners:
        measured_albedo = white_albedo(blocks)
    elif measured_albedo is None:
        measured_albedo = block_albedo(scan, blocks, sensor)
    rows = np.flatnonzero(usable)
    first_rows = rows[::FIRST_ROUND_STRIDE]
    first_coupling = pixel_coupling(first_rows)
    first_albedo = (measured_albedo if white_partners
                    else light_free_albedo(first_coupling.plane, measured_albedo, surfaces.components, 0.0))
    first_fit = fit(first_rows, first_coupling, first_albedo)
    first = first_fit.solve(method, with_amplitude=False, tolerance=EARLY_ROUND_STEP)
    if not (np.isfinite(first.area_m2) and first.area_m2 > 0):  # no multipath to correct for: one round on all
        found = fit(rows, pixel_coupling(rows), first_albedo).solve(method)
        return dataclasses.replace(found, white_surfaces=white_partners)
    # Strong multipath bends each surface near its partners, so the planes through its blocks meet at too
    # sharp an angle and predict too much coupling; the planes of the later rounds rest on the anchors less the
    # bias predicted at the first estimate.
    last_coupling = pixel_coupling(rows, None if reference else first_fit.fixed_planes(first.area_m2))
    if white_partners:  # no albedo to take the multipath's gain off
        found = fit(rows, last_coupling, first_albedo).solve(method, start_m2=first.area_m2)
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
        estimate = fit(rows, last_coupling, albedo).solve(method, start_m2=area)
        if not (np.isfinite(estimate.area_m2) and estimate.area_m2 > 0):
            break
        area = estimate.area_m2
    return estimate


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
