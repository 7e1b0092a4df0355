"""A robust plane per pixel block of a scan, with the area and incidence it covers."""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from mpi_lidar.physics.coupling import vector_length
from mpi_lidar.physics.robust import MAD_TO_SIGMA
from mpi_lidar.scans.geometry._blocks import nanmedian_last, to_blocks

# Range jump [m] within a block beyond which points are taken for another surface in the first plane fit.
EDGE_JUMP_M = 0.1
# Depth sd over a block's lateral spread [1] beyond which its fitted normal is taken for unknown: the noise
# across the plane nears its extent along it, and the smallest principal axis follows the noise.
MAX_NOISE_OVER_SPREAD = 0.7


def fit_block_planes(points: NDArray, b: int, min_share: float = 0.3
                     ) -> tuple[NDArray, NDArray, NDArray, NDArray, NDArray]:
    """Robust plane per b x b block of a point grid (H, W, 3) [m].

    Least-squares plane (smallest principal axis) of the points within ``EDGE_JUMP_M`` of the block's
    median range, then refitted to the points within 3 robust sigmas (and at least 3 mm) of it, so a
    block that straddles a depth edge keeps its main surface.
    Returns centres (Hb, Wb, 3) [m], unit normals (Hb, Wb, 3) towards the scanner, the inlier mask
    (Hb, Wb, b*b), a usable flag (Hb, Wb) (enough finite inliers: ``min_share`` of the block) and the
    RMS distance of the inliers from their plane (Hb, Wb) [m], the depth noise the plane has to beat.
    """
    p = to_blocks(np.asarray(points, dtype=np.float64), b)
    finite = np.isfinite(p).all(-1)
    keep = finite.copy()
    # Start from the points near the block's median range: a far background cannot tilt the first fit.
    distance = np.where(keep, vector_length(np.nan_to_num(p)), np.nan)
    with np.errstate(invalid="ignore"):  # blocks without points compare NaN
        keep &= np.abs(distance - nanmedian_last(distance)[..., None]) <= EDGE_JUMP_M
    centres: NDArray  # both set by the two fits below
    normals: NDArray
    for _ in range(2):
        count = keep.sum(-1)
        weight = keep[..., None]
        safe = np.maximum(count, 1)[..., None]
        centres = np.where(weight, p, 0.0).sum(-2) / safe
        offset = np.where(finite[..., None], p - centres[..., None, :], 0.0)
        x = np.where(weight, offset, 0.0)
        cov = np.matmul(x.swapaxes(-1, -2), x) / safe[..., None]
        cov = np.where(count[..., None, None] >= 3, cov, np.eye(3))
        normals = np.linalg.eigh(cov)[1][..., 0]
        residual = np.abs(np.matmul(offset, normals[..., None])[..., 0])
        mad = nanmedian_last(np.where(keep, residual, np.nan))  # NaN for blocks without points (sky)
        limit = np.maximum(3 * MAD_TO_SIGMA * np.nan_to_num(mad), 0.003)
        keep = finite & (residual <= limit[..., None])
    residual = np.where(keep, residual, 0.0)
    flip = np.einsum("hwi,hwi->hw", normals, centres) > 0
    normals = np.where(flip[..., None], -normals, normals)
    usable = keep.sum(-1) >= max(3, min_share * b * b)
    rms = np.sqrt(np.where(keep, residual**2, 0.0).sum(-1) / np.maximum(keep.sum(-1), 1))
    return centres, normals, keep, usable, rms


def tile_planes(depth: NDArray, band_rays: NDArray, halo_rows: slice, rows: slice, columns: slice, b: int,
                depth_sigma: NDArray | None = None) -> tuple[NDArray, ...]:
    """Block planes of one tile of whole blocks: centres, normals, inliers, usable flags, RMS, plane areas [m^2],
    incidence cosines, the sd of each normal's direction [rad] and of its centre along the normal [m] per block
    (:func:`plane_uncertainty`, from the depth sd map ``depth_sigma`` (H, W) [m] where given), and the tile's
    finite pixels. ``band_rays`` are the rays of ``halo_rows``: the tile's rows and one more on each side where
    the scan has it."""
    w = depth.shape[1]
    d = np.asarray(depth[rows, columns], dtype=np.float64)
    d = np.where(np.isfinite(d) & (d > 0), d, np.nan)
    # One pixel of rays beyond the tile on each side, so the tile's ray steps are those of the whole grid.
    left, right = max(columns.start - 1, 0), min(columns.stop + 1, w)
    halo = band_rays[:, left:right]
    core = (slice(rows.start - halo_rows.start, rows.stop - halo_rows.start),
            slice(columns.start - left, columns.stop - left))
    r = halo[core]
    points = d[..., None] * r
    centres, normals, keep, usable, rms = fit_block_planes(points, b)
    sigma = None if depth_sigma is None else to_blocks(np.asarray(depth_sigma[rows, columns], dtype=np.float64), b)
    normal_sd, centre_sd = plane_uncertainty(to_blocks(points, b), keep, centres, normals, rms, sigma)
    # Pixel footprints on the fitted plane: range^2 times solid angle over the incidence cosine.
    solid_angle = pixel_solid_angle(halo)[core]
    cos_i = np.abs(np.einsum("hwni,hwi->hwn", np.nan_to_num(to_blocks(r, b)), normals))
    pixel_area = to_blocks(d**2 * solid_angle, b) / np.maximum(cos_i, 0.1)
    area = np.where(keep, np.nan_to_num(pixel_area), 0.0).sum(-1)
    centre_ray = centres / np.maximum(np.linalg.norm(centres, axis=-1, keepdims=True), 1e-12)
    block_cos_i = np.maximum(-np.einsum("hwi,hwi->hw", normals, centre_ray), 1e-3)
    return centres, normals, keep, usable, rms, area, block_cos_i, normal_sd, centre_sd, np.isfinite(d)


def plane_uncertainty(points: NDArray, keep: NDArray, centres: NDArray, normals: NDArray, rms: NDArray,
                      sigma: NDArray | None) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """How far the depth noise can turn each block's plane: the sd of its normal's direction [rad] and of its
    centre along the normal [m] (Hb, Wb).

    ``points`` (Hb, Wb, b*b, 3) [m], their inliers ``keep`` (Hb, Wb, b*b), the blocks' ``centres`` (Hb, Wb, 3)
    [m], unit ``normals`` (Hb, Wb, 3) and residual ``rms`` (Hb, Wb) [m] as :func:`fit_block_planes` gives them;
    ``sigma`` (Hb, Wb, b*b) [m] the depth sd of every pixel (the scan's noise at its amplitude), None where not
    known. Depth noise moves a point along its ray, so across the plane by the depth sd times the incidence
    cosine: the root mean square of the inliers' sds times it, or the residual's own estimate where that is
    larger (a normal the noise has turned leaves the noise in the residual; without ``sigma`` the residual is
    all there is). A smallest principal axis of n points of lateral spread s (their rms offset across the line
    of sight along its narrower direction, free of the depth noise) and noise e across the plane turns by
    (e / s) / (sqrt(n) (1 - (e / s)^2)): at a long range the noise nears the block's width, the fit's own
    residual understates it, and where e / s reaches ``MAX_NOISE_OVER_SPREAD`` the normal is taken for
    unknown (an infinite sd). Blocks with fewer than 3 inliers get infinite sds.
    """
    count = keep.sum(-1)
    n = np.maximum(count, 1)
    across = rms * np.sqrt(n / np.maximum(n - 3, 1))  # the plane's three parameters take their share
    line_of_sight = centres / np.maximum(vector_length(centres), 1e-12)[..., None]
    if sigma is not None:
        mean_variance = np.where(keep, np.nan_to_num(sigma) ** 2, 0.0).sum(-1) / n
        cos_i = np.abs(np.einsum("hwi,hwi->hw", normals, line_of_sight))
        across = np.maximum(np.sqrt(mean_variance) * cos_i, across)
    offset = np.where(keep[..., None], np.nan_to_num(points) - centres[..., None, :], 0.0)
    lateral = offset - np.einsum("hwni,hwi->hwn", offset, line_of_sight)[..., None] * line_of_sight[..., None, :]
    spread = np.linalg.eigvalsh(np.matmul(lateral.swapaxes(-1, -2), lateral) / n[..., None, None])[..., 1]
    with np.errstate(divide="ignore", invalid="ignore"):
        ratio = across / np.sqrt(np.maximum(spread, 0.0))
        # The smallest principal axis turns by the points' cross moment over the gap between the lateral and the
        # noise variances; where the noise nears the spread, that axis is any.
        known = (count >= 3) & (ratio < MAX_NOISE_OVER_SPREAD)
        normal_sd = np.where(known, ratio / (np.sqrt(n) * (1.0 - np.where(known, ratio, 0.0) ** 2)), np.inf)
    centre_sd = np.where(count >= 3, across / np.sqrt(n), np.inf)
    return normal_sd, centre_sd


def pixel_solid_angle(rays: NDArray) -> NDArray[np.float64]:
    """Solid angle per pixel (H, W) [sr] of a ray grid, from the cross product of neighbouring ray steps."""
    h, w = rays.shape[:2]
    du = np.gradient(rays, axis=1) if w > 1 else np.zeros_like(rays)
    dv = np.gradient(rays, axis=0) if h > 1 else np.zeros_like(rays)
    # |du x dv| written out: the same numbers as np.linalg.norm(np.cross(du, dv), axis=-1), at a tenth of the cost.
    cross = (du[..., 1] * dv[..., 2] - du[..., 2] * dv[..., 1], du[..., 2] * dv[..., 0] - du[..., 0] * dv[..., 2],
             du[..., 0] * dv[..., 1] - du[..., 1] * dv[..., 0])
    return vector_length(np.stack(cross, axis=-1))
