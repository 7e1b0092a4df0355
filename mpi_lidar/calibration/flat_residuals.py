"""Residuals of a scan's flat surfaces: each frequency's depth minus its block's plane, away from multipath and edges.

On a flat surface without multipath, a frequency's depth minus the surface's plane is that frequency's noise plus
its fixed offset: what :func:`mpi_lidar.calibration.sensor_scale.estimate_sensor_scale` measures the amplitude
unit, the noise scale and the offsets from.

Planes. :func:`flat_surface_residuals` fits each block's plane to the depth averaged over the F frequencies,
d_mean, so that no frequency is fitted more closely than another. With the plane's hat matrix H (leverage h_i of
pixel i, h = 3 / m on average for m pixels), r_f = e_f - (H e_mean)_i, and

    Var r_f = s_f^2 (1 - 2 h_i / F) + h_i / F^2 sum_g s_g^2,                                  (S1)

the degrees of freedom the fit takes: each pixel's leverage comes with its residuals, so that the estimator uses
(S1), not s_f^2. A plane fitted to the highest frequency alone would shrink that frequency's variance by (1 - h_i)
and inflate the others' by h_i s_F^2, and its outlier trimming would truncate the highest frequency's residuals
only. The plane also takes up the offsets' mean: only differences between frequencies are left in the residuals.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from mpi_lidar.config import SensorConfig
from mpi_lidar.correction.footprint import surface_labels
from mpi_lidar.correction.options import AUTO, CorrectionOptions
from mpi_lidar.correction.scene import SceneGeometry, scene_blocks
from mpi_lidar.physics.coupling import DEFAULT_FOOTPRINT_AREA_M2
from mpi_lidar.physics.robust import MAD_TO_SIGMA
from mpi_lidar.physics.window import window_corrections_m
from mpi_lidar.scans import geometry
from mpi_lidar.scans.scan import Scan

# Pixels taken at most (whole blocks, evenly spaced), and the most the estimator evaluates its likelihood on: beyond
# some 10^5 the sigmas are far below the noise model's own systematic errors.
MAX_PIXELS = 100_000
# Flat pixels are taken only where the expected multipath bias stays below this [m] at a generous footprint:
# a few times the default effective footprint, or the given one if larger.
MAX_FLAT_BIAS_M = 2e-5
GENEROUS_FOOTPRINT_FACTOR = 4.0
# A block is taken only when its plane (fitted to the highest frequency) kept this share of its pixels: a block
# that straddles a depth edge keeps one side only, and its label speaks for that side alone.
MIN_KEPT_SHARE = 0.9
# A pixel's residuals count when its mean depth lies within this many robust sigmas of its block's plane: wide
# enough that no residual is truncated (a Gaussian passes 6 sigmas once in 5e8), narrow enough to leave out a
# pixel of another surface.
PLANE_WINDOW_SIGMAS = 6.0
# A cell's eight neighbours, itself left out.
_EIGHT_NEIGHBOURS = np.array([[1, 1, 1], [1, 0, 1], [1, 1, 1]], dtype=bool)


@dataclass(frozen=True)
class FlatSurfaceResiduals:
    """Each frequency's depth minus its block's plane on a scan's flat surfaces, away from multipath and edges
    (:func:`flat_surface_residuals`).

    Attributes
    ----------
    amplitude : NDArray[np.float64]
        Amplitude (n, F) as the scan reports it. [scanner units]
    residual_m : NDArray[np.float64]
        Depth minus the plane's depth along the pixel's ray (n, F), the plane fitted to the mean depth over the
        frequencies. [m]
    leverage : NDArray[np.float64]
        The plane fit's leverage h of each pixel (n,): its block's hat-matrix diagonal, 3 / m on average. [1]
    pixels : NDArray[np.intp]
        Flat indices (n,) of the pixels in the scan's (H, W) grid.
    blocks : int
        The blocks the pixels lie in.
    """

    amplitude: NDArray[np.float64]
    residual_m: NDArray[np.float64]
    leverage: NDArray[np.float64]
    pixels: NDArray[np.intp]
    blocks: int = 0


def flat_surface_residuals(scan: Scan, usable_depth: NDArray, options: CorrectionOptions, *,
                           scene: SceneGeometry | None = None, max_pixels: int = MAX_PIXELS,
                           window_sensor: SensorConfig | None = None) -> FlatSurfaceResiduals:
    """Each frequency's depth minus its block's plane, on the inner blocks of the scan's flat surfaces that no
    surface faces.

    A block is taken when it and its eight neighbours lie on one flat surface
    (:func:`~mpi_lidar.correction.footprint.surface_labels`: no depth edge, no bend within a block of it), none
    of them has a multipath bias above ``MAX_FLAT_BIAS_M`` at a generous footprint (``GENEROUS_FOOTPRINT_FACTOR``
    times the default effective footprint, or the given one if larger), and its own plane kept ``MIN_KEPT_SHARE``
    of its pixels. Each taken block's plane is fitted again, to the mean depth over the frequencies
    (:func:`mpi_lidar.scans.geometry.fit_block_planes`, its robust fit). A pixel of the block gets residuals when
    its depth is usable, no neighbour of it is off its own block's plane (an edge's mixed pixels) and its mean depth
    lies within ``PLANE_WINDOW_SIGMAS`` of the plane: the pixels the fit trimmed count too, so that no frequency's
    residuals are truncated.

    Multipath from surfaces beyond ``options.partner_range_m`` is not seen (the blocks pair only within it): on the
    far halves of a 90-degree corner of 1.2 m boards it leaves the pixels taken a bias of up to 1 mm, 0.1 mm on
    average between frequencies, which reads as part of the depth offsets and is far below the noise the scales are
    measured on.

    Parameters
    ----------
    scan : Scan
        The scan (its maps may stay in the store).
    usable_depth : NDArray
        Highest-frequency depth (H*W,) of the usable pixels, NaN elsewhere. [m] Where the amplitude's units are not
        known, make it from the depths alone (finite, frequencies consistent): amplitude thresholds in V^2 would
        take a scan in other units for saturated or dark.
    options : CorrectionOptions
        Block size, partner range, footprint and tile size of the scene geometry.
    scene : SceneGeometry | None
        The scan's scene geometry where it was analysed already (its blocks and surfaces are used).
    max_pixels : int
        At most this many pixels: whole blocks, evenly spaced among those taken.
    window_sensor : SensorConfig | None
        Where given, each frequency's depth has this sensor's integration window's leakage removed first.

    Returns
    -------
    FlatSurfaceResiduals
        Amplitudes, residuals, leverages and pixel indices; none for a scan without geometry or flat surfaces.
    """
    frequencies = len(scan.frequencies_hz)
    blocks = scene.blocks if scene is not None and scene.blocks is not None else scene_blocks(scan, usable_depth,
                                                                                               options)
    if blocks is None:
        return _no_residuals(frequencies)
    labels = scene.surfaces if scene is not None and scene.surfaces is not None else surface_labels(blocks)
    chosen = np.flatnonzero(_quiet_inner_blocks(blocks, labels.flat, options))
    per_block = blocks.block_pixels**2
    if chosen.size * per_block > max_pixels:  # evenly spaced whole blocks, so every surface keeps its share
        keep = max(1, max_pixels // per_block)
        chosen = chosen[np.linspace(0, chosen.size - 1, keep).round().astype(np.intp)]
    if chosen.size == 0:
        return _no_residuals(frequencies)
    return _block_residuals(scan, usable_depth, blocks, chosen, window_sensor)


def _no_residuals(frequencies: int) -> FlatSurfaceResiduals:
    return FlatSurfaceResiduals(np.zeros((0, frequencies)), np.zeros((0, frequencies)), np.zeros(0),
                                np.zeros(0, dtype=np.intp))


def _quiet_inner_blocks(blocks: geometry.FacingBlocks, flat: NDArray, options: CorrectionOptions) -> NDArray:
    """Blocks (Hb*Wb,) that lie with their eight neighbours on one flat surface, none of the nine reaching a
    multipath bias of ``MAX_FLAT_BIAS_M`` at a generous footprint, whose plane kept ``MIN_KEPT_SHARE`` of its
    pixels.

    Pixels interpolate block values from the neighbouring blocks, so a block is as quiet as its neighbourhood;
    past the scan's border a block is its own neighbour.
    """
    hb, wb = blocks.usable.shape
    labels = flat.reshape(hb, wb)
    padded = np.pad(labels, 1, mode="edge")
    inner = labels >= 0
    for dy in (-1, 0, 1):
        for dx in (-1, 0, 1):
            inner &= padded[1 + dy:1 + dy + hb, 1 + dx:1 + dx + wb] == labels
    given = 0.0 if options.footprint_area_m2 == AUTO else float(options.footprint_area_m2)
    footprint_m2 = max(given, GENEROUS_FOOTPRINT_FACTOR * DEFAULT_FOOTPRINT_AREA_M2)
    bias_m = blocks.block_potential(footprint_m2).bias_m.reshape(hb, wb)
    from scipy.ndimage import maximum_filter

    # A block without a bias (NaN) counts as loud, for itself and its neighbours.
    loud = np.where(np.isnan(bias_m), np.inf, bias_m)
    quiet = maximum_filter(loud, size=3, mode="nearest") <= MAX_FLAT_BIAS_M
    finite = np.nansum(geometry.to_blocks(blocks.finite.astype(np.float64), blocks.block_pixels), axis=-1)
    whole = blocks.keep.sum(-1) >= MIN_KEPT_SHARE * finite
    return (inner & quiet & whole).ravel()


def _block_residuals(scan: Scan, usable_depth: NDArray, blocks: geometry.FacingBlocks,
                     chosen: NDArray, window_sensor: SensorConfig | None = None) -> FlatSurfaceResiduals:
    """Residuals of the pixels of the blocks ``chosen`` (K,) (flat block indices) from planes fitted to their mean
    depth over the frequencies; only pixels whose mean depth lies within ``PLANE_WINDOW_SIGMAS`` of the plane.
    With ``window_sensor``, of the depths less that sensor's window leakage."""
    b = blocks.block_pixels
    pixels = _pixels_of_blocks(blocks, chosen)
    present = np.flatnonzero(pixels >= 0)
    y, x = np.divmod(pixels[present], blocks.shape[1])
    depth = np.full((pixels.size, len(scan.frequencies_hz)), np.nan)
    depth[present] = np.asarray(scan.depth[:, y, x], dtype=np.float64).T
    amplitude = np.full_like(depth, np.nan)
    amplitude[present] = np.asarray(scan.amplitude[:, y, x], dtype=np.float64).T
    if window_sensor is not None:
        depth[present] += window_corrections_m(depth[present], amplitude[present], scan.frequencies_hz, window_sensor)
    rays = np.full((pixels.size, 3), np.nan)
    rays[present] = scan.pixel_rays(y, x)
    usable = np.zeros(pixels.size, dtype=bool)
    usable[present] = (np.isfinite(np.asarray(usable_depth).reshape(-1)[pixels[present]])
                       & ~_beside_other_surfaces(blocks).reshape(-1)[pixels[present]])
    usable &= np.isfinite(depth).all(1) & np.isfinite(amplitude).all(1)
    mean_depth = np.where(usable, depth.mean(1), np.nan)
    plane_depth, fitted = _mean_depth_planes(mean_depth, rays, chosen.size, b)
    with np.errstate(invalid="ignore"):  # pixels without a depth or a plane
        off_plane = np.abs(mean_depth - plane_depth).reshape(chosen.size, b * b)
        spread = MAD_TO_SIGMA * geometry.nanmedian_last(np.where(fitted, off_plane, np.nan))
        near = (off_plane <= PLANE_WINDOW_SIGMAS * spread[:, None]).reshape(-1)
    leverage = _plane_leverage(fitted, b).reshape(-1)
    take = usable & near & np.isfinite(plane_depth) & np.isfinite(leverage)
    return FlatSurfaceResiduals(amplitude[take], depth[take] - plane_depth[take, None], leverage[take],
                                pixels[take].astype(np.intp), int(np.unique(np.flatnonzero(take) // (b * b)).size))


def _beside_other_surfaces(blocks: geometry.FacingBlocks) -> NDArray[np.bool_]:
    """Pixels (H, W) with one of their eight neighbours off its block's plane or without a depth: next to a depth
    edge, where a real scan's pixels mix two surfaces.

    A pixel's own distance from the plane does not count, so that the pixels the fit trimmed for their noise keep
    their residuals, and their neighbours, left out for it, are left out whatever their own noise.
    """
    from scipy.ndimage import binary_dilation

    hb, wb = blocks.usable.shape
    b = blocks.block_pixels
    height, width = blocks.shape
    inlier = blocks.keep.reshape(hb, wb, b, b).swapaxes(1, 2).reshape(hb * b, wb * b)[:height, :width]
    return binary_dilation(~inlier, structure=_EIGHT_NEIGHBOURS)


def _pixels_of_blocks(blocks: geometry.FacingBlocks, chosen: NDArray) -> NDArray[np.intp]:
    """Flat pixel indices (K b b,) of the blocks ``chosen`` (K,), block by block, each row by row; -1 past the
    scan's edge."""
    b = blocks.block_pixels
    height, width = blocks.shape
    block_row, block_column = np.divmod(chosen, blocks.usable.shape[1])
    ys = np.broadcast_to(block_row[:, None, None] * b + np.arange(b)[None, :, None], (chosen.size, b, b))
    xs = np.broadcast_to(block_column[:, None, None] * b + np.arange(b)[None, None, :], (chosen.size, b, b))
    return np.where((ys < height) & (xs < width), ys * width + xs, -1).reshape(-1)


def _mean_depth_planes(mean_depth: NDArray, rays: NDArray, count: int, b: int) -> tuple[NDArray, NDArray]:
    """The plane's depth along each pixel's ray (K b b,) [m] from the robust plane of each of K blocks' mean
    depths (K b b,) [m] along their rays (K b b, 3), and the pixels the fit kept (K, b*b).

    The blocks are laid side by side in a grid of b rows and K b columns, so that one call of
    :func:`~mpi_lidar.scans.geometry.fit_block_planes` fits them all; NaN where a block has no plane.
    """
    # (K, b, b, 3) -> (b, K b, 3): block k's pixel (row, column) at grid (row, k b + column).
    points = (mean_depth[:, None] * rays).reshape(count, b, b, 3).swapaxes(0, 1).reshape(b, count * b, 3)
    with np.errstate(invalid="ignore", divide="ignore"):  # blocks left without points
        centres, normals, keep, usable, _ = geometry.fit_block_planes(points, b)
        block_of = np.repeat(np.arange(count), b * b)
        plane_depth = (np.einsum("ki,ki->k", normals[0], centres[0])[block_of]
                       / np.einsum("ni,ni->n", normals[0][block_of], rays))
    plane_depth[~usable[0][block_of]] = np.nan
    return plane_depth, keep[0] & usable[0][:, None]


def _plane_leverage(fitted: NDArray, b: int) -> NDArray[np.float64]:
    """Leverage (K, b*b) of each pixel of K blocks in a least-squares plane over the pixels ``fitted`` (K, b*b).

    The plane is linear in the pixel's row and column within a block (the ray's angles, to first order), and a
    leverage does not change under an affine change of the regressors: h = x^T (X^T X)^-1 x with x = (1, row,
    column) and X the fitted pixels' rows. The few pixels the robust fit trimmed get the same x^T (X^T X)^-1 x, the
    leverage of a prediction: (S1) understates their variance by 2 h s_f^2 / F, a negligible error on so few.
    """
    row, column = np.divmod(np.arange(b * b), b)
    x = np.column_stack([np.ones(b * b), row, column]).astype(np.float64)  # (b*b, 3)
    weight = fitted.astype(np.float64)
    gram = np.einsum("kn,ni,nj->kij", weight, x, x)  # X^T X per block (K, 3, 3)
    # A block with fewer than three pixels in a line has a singular Gram matrix: no leverage, and no residuals.
    singular = np.linalg.matrix_rank(gram) < 3
    gram[singular] = np.eye(3)
    inverse = np.linalg.inv(gram)
    leverage = np.einsum("ni,kij,nj->kn", x, inverse, x)
    leverage[singular] = np.nan
    return leverage
