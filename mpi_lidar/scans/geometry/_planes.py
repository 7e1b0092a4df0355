"""A robust plane per pixel block of a scan, with the area and incidence it covers."""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from mpi_lidar.physics.coupling import vector_length
from mpi_lidar.physics.robust import MAD_TO_SIGMA
from mpi_lidar.scans.geometry._blocks import nanmedian_last, to_blocks

# Range jump [m] within a block beyond which points are taken for another surface in the first plane fit.
EDGE_JUMP_M = 0.1


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


def tile_planes(depth: NDArray, band_rays: NDArray, halo_rows: slice, rows: slice, columns: slice, b: int
                 ) -> tuple[NDArray, ...]:
    """Block planes of one tile of whole blocks: centres, normals, inliers, usable flags, RMS, plane areas [m^2]
    and incidence cosines per block, and the tile's finite pixels. ``band_rays`` are the rays of
    ``halo_rows``: the tile's rows and one more on each side where the scan has it."""
    w = depth.shape[1]
    d = np.asarray(depth[rows, columns], dtype=np.float64)
    d = np.where(np.isfinite(d) & (d > 0), d, np.nan)
    # One pixel of rays beyond the tile on each side, so the tile's ray steps are those of the whole grid.
    left, right = max(columns.start - 1, 0), min(columns.stop + 1, w)
    halo = band_rays[:, left:right]
    core = (slice(rows.start - halo_rows.start, rows.stop - halo_rows.start),
            slice(columns.start - left, columns.stop - left))
    r = halo[core]
    centres, normals, keep, usable, rms = fit_block_planes(d[..., None] * r, b)
    # Pixel footprints on the fitted plane: range^2 times solid angle over the incidence cosine.
    solid_angle = pixel_solid_angle(halo)[core]
    cos_i = np.abs(np.einsum("hwni,hwi->hwn", np.nan_to_num(to_blocks(r, b)), normals))
    pixel_area = to_blocks(d**2 * solid_angle, b) / np.maximum(cos_i, 0.1)
    area = np.where(keep, np.nan_to_num(pixel_area), 0.0).sum(-1)
    centre_ray = centres / np.maximum(np.linalg.norm(centres, axis=-1, keepdims=True), 1e-12)
    block_cos_i = np.maximum(-np.einsum("hwi,hwi->hw", normals, centre_ray), 1e-3)
    return centres, normals, keep, usable, rms, area, block_cos_i, np.isfinite(d)


def pixel_solid_angle(rays: NDArray) -> NDArray[np.float64]:
    """Solid angle per pixel (H, W) [sr] of a ray grid, from the cross product of neighbouring ray steps."""
    h, w = rays.shape[:2]
    du = np.gradient(rays, axis=1) if w > 1 else np.zeros_like(rays)
    dv = np.gradient(rays, axis=0) if h > 1 else np.zeros_like(rays)
    # |du x dv| written out: the same numbers as np.linalg.norm(np.cross(du, dv), axis=-1), at a tenth of the cost.
    cross = (du[..., 1] * dv[..., 2] - du[..., 2] * dv[..., 1], du[..., 2] * dv[..., 0] - du[..., 0] * dv[..., 2],
             du[..., 0] * dv[..., 1] - du[..., 1] * dv[..., 0])
    return vector_length(np.stack(cross, axis=-1))
