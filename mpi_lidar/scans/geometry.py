"""Geometry from a scan: point clouds, surface normals, and where multipath can exist (point-cloud files:
:mod:`mpi_lidar.scans.pointcloud`)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol

import numpy as np
from numpy.typing import NDArray

from mpi_lidar.physics.coupling import DEFAULT_FOOTPRINT_AREA_M2, footprint_coupling, pair_geometry, vector_length
from mpi_lidar.scans.neighbours import bilinear, pairs_within
from mpi_lidar.threads import on_cores


def point_cloud(depth: NDArray, rays: NDArray) -> NDArray[np.float64]:
    """Points (H, W, 3) [m] of a range map (H, W) [m] along unit rays (H, W, 3)."""
    return np.asarray(depth, dtype=np.float64)[..., None] * np.asarray(rays, dtype=np.float64)


def surface_normals(points: NDArray) -> NDArray[np.float64]:
    """Unit normals (H, W, 3) from central differences of the point grid, oriented towards the scanner.

    Pixels whose neighbourhood holds a non-finite point get NaN normals.
    """
    p = np.asarray(points, dtype=np.float64)
    du = np.gradient(p, axis=1)
    dv = np.gradient(p, axis=0)
    n = np.cross(du, dv)
    length = np.linalg.norm(n, axis=-1, keepdims=True)
    n = np.divide(n, length, out=np.full_like(n, np.nan), where=length > 0)
    facing_away = np.einsum("hwk,hwk->hw", n, p) > 0
    n[facing_away] *= -1
    return n


# --- multipath potential -----------------------------------------------------------------------------------

# The effective receiver footprint A_fp [m^2] of the A -> B -> A coupling, 90 pi (12 mm)^2, is defined with
# its kernel in mpi_lidar.physics.coupling (DEFAULT_FOOTPRINT_AREA_M2, imported above).
DEFAULT_BLOCK_M = 0.03
DEFAULT_MAX_RANGE_M = 0.5
DEFAULT_MIN_COS = 0.1
# Range jump [m] within a block beyond which points are taken for another surface in the first plane fit.
EDGE_JUMP_M = 0.1
# Pixels per tile of whole blocks that the plane fits work on at once (and per band of rows the potential
# is interpolated on): their float64 temporaries take about 300 bytes a pixel, so a tile bounds the memory
# whatever the scan's size.
BAND_PIXELS = 262_144
# 1 / sqrt(coupling) [1] standing in for a block without coupling when coupling is interpolated.
NO_COUPLING_ROOT = 1e3
# Largest block side [px]. Blocks keep their metric size up to it, so a finer grid has bigger blocks, not
# more of them: the facing pairs grow with the square of the block count.
MAX_BLOCK_PIXELS = 512


@dataclass(frozen=True)
class MultipathPotential:
    """Per pixel (H, W): what the scan's own geometry says about the multipath A -> B -> A at A.

    ``coupling`` is the simulator's kappa with a white partner (b = 1): sum over facing patches B of
    (cos_A cos_B)^2 dA_B A_fp / (pi^2 r^4 cos_i), capped at 1 [1]. ``d_ab_m`` is the coupling-weighted
    mean A-B distance [m] (NaN where the coupling is 0). ``bias_m`` = coupling * d_ab_m, the depth bias
    of that multipath in the small-phase limit for white surfaces (Gamma_M / Gamma_D times the extra
    range) [m]: an upper scale of the bias, zero where no surface faces A. ``block_pixels`` is the side
    of the pixel blocks the planes were fitted to.
    """

    coupling: NDArray[np.float64]
    d_ab_m: NDArray[np.float64]
    bias_m: NDArray[np.float64]
    block_pixels: int


class RayRowsLike(Protocol):
    """Unit rays (H, W, 3) read a band of rows at a time (``rays[top:bottom]``): an array or a scan's
    :class:`mpi_lidar.scans.scan.RayRows`, which builds each band only when asked."""

    @property
    def shape(self) -> tuple[int, ...]: ...

    def __getitem__(self, rows: slice, /) -> NDArray: ...


def block_size_pixels(depth: NDArray, rays: NDArray | RayRowsLike, block_m: float) -> int:
    """Side of a square pixel block spanning about ``block_m`` [m] at the scan's median range (4 to
    :data:`MAX_BLOCK_PIXELS`).

    ``rays`` (H, W, 3) may be anything that gives rows of rays by slicing (:class:`mpi_lidar.scans.scan.RayRows`):
    only the two centre rows are read.
    """
    h, w = rays.shape[:2]
    cy, cx = h // 2, w // 2
    top = min(cy, max(h - 2, 0))
    r = np.asarray(rays[top:min(h, cy + 2)], dtype=np.float64)
    steps = []
    if w > 1:
        steps.append(np.arccos(np.clip(r[cy - top, min(cx, w - 2)] @ r[cy - top, min(cx, w - 2) + 1], -1, 1)))
    if h > 1:
        steps.append(np.arccos(np.clip(r[min(cy, h - 2) - top, cx] @ r[min(cy, h - 2) + 1 - top, cx], -1, 1)))
    values = np.asarray(depth)
    finite = values[np.isfinite(values) & (values > 0)]
    if not steps or finite.size == 0 or max(steps) <= 0:
        return 4
    pitch_m = float(_median(finite)) * max(steps)
    return int(np.clip(round(block_m / pitch_m), 4, MAX_BLOCK_PIXELS))


def _median(values: NDArray) -> np.floating:
    """np.median of ``values`` taken in float64, without a float64 copy of them all (float32 widens exactly)."""
    n = values.size
    middle = np.partition(values.ravel(), [(n - 1) // 2, n // 2])[[(n - 1) // 2, n // 2]].astype(np.float64)
    return middle[0] if n % 2 else np.mean(middle)


def block_row_bands(height: int, width: int, block_pixels: int, band_pixels: int) -> list[slice]:
    """Row ranges of whole block rows, about ``band_pixels`` pixels each (at least one block row)."""
    rows = max(1, band_pixels // max(width * block_pixels, 1)) * block_pixels
    return [slice(top, min(top + rows, height)) for top in range(0, height, rows)]


def block_tiles(height: int, width: int, block_pixels: int, tile_pixels: int) -> list[list[tuple[slice, slice]]]:
    """Tiles of whole blocks, about ``tile_pixels`` pixels each (at least one block): per band of block rows,
    its (rows, columns) tiles from left to right."""
    tiles = []
    for rows in block_row_bands(height, width, block_pixels, tile_pixels):
        side = rows.stop - rows.start
        columns = max(1, tile_pixels // max(side * block_pixels, 1)) * block_pixels
        tiles.append([(rows, slice(left, min(left + columns, width))) for left in range(0, width, columns)])
    return tiles


def nanmedian_last(values: NDArray) -> NDArray[np.float64]:
    """np.nanmedian over the last axis, NaN where a row has only NaN, without its warnings.

    One sort of all rows at once (NaN sorts last) and the middle of each row's other values: the same
    numbers as np.nanmedian, which works row by row and costs ten times as much on blocks of a few hundred.
    """
    ordered = np.sort(values, axis=-1)
    count = (~np.isnan(values)).sum(-1, keepdims=True)
    low = np.take_along_axis(ordered, np.maximum(count - 1, 0) // 2, axis=-1)
    high = np.take_along_axis(ordered, np.minimum(count // 2, values.shape[-1] - 1), axis=-1)
    return np.where(count > 0, (low + high) / 2, np.nan)[..., 0]


def to_blocks(values: NDArray, b: int) -> NDArray:
    """(H, W, ...) -> (Hb, Wb, b*b, ...), padded with NaN to whole blocks."""
    h, w = values.shape[:2]
    hb, wb = -(-h // b), -(-w // b)
    padded = np.full((hb * b, wb * b, *values.shape[2:]), np.nan)
    padded[:h, :w] = values
    shaped = padded.reshape(hb, b, wb, b, *values.shape[2:]).swapaxes(1, 2)
    return shaped.reshape(hb, wb, b * b, *values.shape[2:])


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
        limit = np.maximum(3 * 1.4826 * np.nan_to_num(mad), 0.003)
        keep = finite & (residual <= limit[..., None])
    residual = np.where(keep, residual, 0.0)
    flip = np.einsum("hwi,hwi->hw", normals, centres) > 0
    normals = np.where(flip[..., None], -normals, normals)
    usable = keep.sum(-1) >= max(3, min_share * b * b)
    rms = np.sqrt(np.where(keep, residual**2, 0.0).sum(-1) / np.maximum(keep.sum(-1), 1))
    return centres, normals, keep, usable, rms


def multipath_potential(depth: NDArray, rays: NDArray, *, block_m: float = DEFAULT_BLOCK_M,
                        max_range_m: float = DEFAULT_MAX_RANGE_M,
                        footprint_area_m2: float = DEFAULT_FOOTPRINT_AREA_M2,
                        min_cos: float = DEFAULT_MIN_COS) -> MultipathPotential:
    """Where multipath can exist in a scan, from its range map (H, W) [m] and unit rays (H, W, 3).

    The scan is cut into square blocks of about ``block_m`` [m]; a robust plane per block (centre, normal,
    area) stands in for its surface, so the raw depth's noise and its own smooth multipath bias do not
    make fake partners. For each pair of blocks A, B closer than ``max_range_m`` [m] that face each other
    (cos_A, cos_B > ``min_cos``, and each centre further from the other's plane than three times the
    two fits' residual RMS, so noisy planes of one surface never face each other), B couples to A with
    the scene simulator's kappa_B = (cos_A cos_B)^2 dA_B A_fp / (pi^2 r^4 cos_i) (the one kernel of
    :mod:`mpi_lidar.physics.coupling`; r clamped below by the block size, the sum capped at 1). A plane, a
    convex surface or open sky has no facing pair: zero everywhere. Block values are interpolated bilinearly to pixels.
    Occlusion between A and B is ignored, and surfaces outside the scan's field of view are not known.
    Everything but the footprint is in :func:`facing_blocks`; this is ``facing_blocks(...).potential(A_fp)``.
    """
    return facing_blocks(depth, rays, block_m=block_m, max_range_m=max_range_m,
                         min_cos=min_cos).potential(footprint_area_m2)


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


@dataclass(frozen=True)
class FacingBlocks:
    """A scan's block planes and the block pairs that face each other: the potential up to the footprint.

    Block arrays are (Hb, Wb, ...) as :func:`fit_block_planes` returns them; ``index`` holds the flat
    indices of the usable blocks, in the order the pairs refer to; ``shape`` is the scan's (H, W) and
    ``finite`` (H, W) marks the pixels with a point.
    """

    shape: tuple[int, int]
    block_pixels: int
    centres: NDArray[np.float64]
    normals: NDArray[np.float64]
    keep: NDArray[np.bool_]
    usable: NDArray[np.bool_]
    rms_m: NDArray[np.float64]
    index: NDArray[np.intp]
    pairs: FacingPairs
    finite: NDArray[np.bool_]

    def bands(self, band_pixels: int = BAND_PIXELS) -> list[slice]:
        """Row ranges of whole block rows, about ``band_pixels`` pixels each (:func:`block_row_bands`)."""
        return block_row_bands(*self.shape, self.block_pixels, band_pixels)

    def tiles(self, tile_pixels: int = BAND_PIXELS) -> list[list[tuple[slice, slice]]]:
        """Tiles of whole blocks, about ``tile_pixels`` each, per band of block rows (:func:`block_tiles`)."""
        return block_tiles(*self.shape, self.block_pixels, tile_pixels)

    def block_grid(self, rows: slice = slice(None)) -> tuple[NDArray, NDArray]:
        """Block coordinates (rows, W) of the pixel centres of ``rows``, for bilinear interpolation of block values."""
        h, w = self.shape
        ys = (np.arange(h)[rows] + 0.5) / self.block_pixels - 0.5
        xs = (np.arange(w) + 0.5) / self.block_pixels - 0.5
        grid = np.meshgrid(ys, xs, indexing="ij")
        return grid[0], grid[1]

    def pixel_coordinates(self, pixels: NDArray) -> tuple[NDArray, NDArray]:
        """Block coordinates of the centres of flat pixel indices (n,), as :meth:`block_grid` gives them."""
        ys, xs = np.divmod(np.asarray(pixels), self.shape[1])
        return (ys + 0.5) / self.block_pixels - 0.5, (xs + 0.5) / self.block_pixels - 0.5

    def to_pixels(self, block_values: NDArray, coordinates: tuple[NDArray, NDArray] | None = None) -> NDArray:
        """Bilinear interpolation of one value per block (Hb*Wb,) at pixel coordinates (default: every pixel),
        the edge blocks' values continued beyond them."""
        hb, wb = self.usable.shape
        rows, columns = self.block_grid() if coordinates is None else coordinates
        return bilinear(block_values.reshape(hb, wb), rows, columns)

    def coupling_to_pixels(self, block_values: NDArray, coordinates: tuple[NDArray, NDArray]) -> NDArray:
        """A coupling per block (Hb*Wb,) at pixel coordinates, 0 where it reaches no block with coupling.

        Near an edge the coupling falls as 1 / a^2 with the distance a from it, so a linear interpolation
        between block centres would overstate it between them (by up to 2x a few centimetres from the edge);
        1 / sqrt(coupling) is linear in a and is interpolated instead.
        """
        has = block_values > 0
        root = self.to_pixels(np.where(has, np.where(has, block_values, 1.0) ** -0.5, NO_COUPLING_ROOT), coordinates)
        # Rounding leaves a pixel among blocks without coupling a hair below the stand-in: no coupling either.
        return np.where(root < NO_COUPLING_ROOT * (1 - 1e-9), root**-2.0, 0.0)

    def potential(self, footprint_area_m2: float) -> MultipathPotential:
        """The multipath potential of every pixel for the footprint A_fp [m^2] (:func:`multipath_potential`)."""
        return self.block_potential(footprint_area_m2).rows()

    def block_potential(self, footprint_area_m2: float) -> BlockPotential:
        """Coupling and bias per block for the receiver footprint A_fp [m^2]; pixels interpolate them."""
        hb, wb = self.usable.shape
        coupling_blocks = np.zeros(hb * wb)
        weighted_r = np.zeros(hb * wb)
        if self.pairs.a.size:
            kappa = self.pairs.kappa(footprint_area_m2)
            coupling_blocks[self.index] = np.bincount(self.pairs.a, kappa, minlength=self.index.size)
            weighted_r[self.index] = np.bincount(self.pairs.a, kappa * self.pairs.distance_m,
                                                 minlength=self.index.size)
        with np.errstate(invalid="ignore", divide="ignore"):
            d_ab_blocks = np.where(coupling_blocks > 0, weighted_r / coupling_blocks, 0.0)
        coupling_blocks = np.minimum(coupling_blocks, 1.0)
        return BlockPotential(self, coupling_blocks, coupling_blocks * d_ab_blocks)

    def equivalent_rho_aba(self, footprint_area_m2: float, albedo: NDArray) -> EquivalentRhoAba:
        """What a correction model needs per block for the footprint A_fp [m^2] and the albedo of every block
        (Hb*Wb,): the rho_ABA and d_AB [m] of the surface facing the sensor that shows the same multipath.

        A pixel at incidence cos_i on a surface of albedo a returns a cos_i of the light a facing surface of
        albedo a returns, so its amplitude reads as the albedo a cos_i; its multipath ratio is
        a sum_B b_B kappa_B. The facing surface of albedo a cos_i shows that ratio with
        rho_ABA = sum_B b_B kappa_B / cos_i: each pair's kappa weighted by its partner's albedo, over A's
        incidence cosine, the white kappa's sum capped at 1 as in :meth:`block_potential`. d_AB is weighted
        by the same terms.
        """
        blocks = self.usable.size
        rho_aba = np.zeros(blocks)
        d_ab = np.zeros(blocks)
        if self.pairs.a.size:
            kappa = self.pairs.kappa(footprint_area_m2)
            white = np.bincount(self.pairs.a, kappa, minlength=self.index.size)
            term = kappa * albedo[self.index[self.pairs.b]] / self.pairs.cos_i
            weighted = np.bincount(self.pairs.a, term, minlength=self.index.size)
            with np.errstate(invalid="ignore", divide="ignore"):
                d_ab[self.index] = np.where(weighted > 0, np.bincount(self.pairs.a, term * self.pairs.distance_m,
                                                                      minlength=self.index.size) / weighted, 0.0)
            rho_aba[self.index] = weighted / np.maximum(white, 1.0)
        return EquivalentRhoAba(self, rho_aba, d_ab)


@dataclass(frozen=True)
class BlockPotential:
    """The multipath potential per block (Hb*Wb,) for one footprint: the coupling (capped at 1) and the bias
    [m]. Pixels get both by bilinear interpolation, a band of rows or a set of pixels at a time, so the
    whole scan's float64 maps never exist at once; every pixel gets the same value either way."""

    blocks: FacingBlocks
    coupling: NDArray[np.float64]
    bias_m: NDArray[np.float64]

    def rows(self, rows: slice = slice(None)) -> MultipathPotential:
        """The potential (rows, W) of a range of rows."""
        grid = self.blocks.block_grid(rows)
        return self._at(grid, self.blocks.finite[rows])

    def bias_rows(self, rows: slice = slice(None)) -> NDArray[np.float64]:
        """The bias [m] (rows, W) of a range of rows alone, as :meth:`rows` gives it."""
        bias = self.blocks.to_pixels(self.bias_m, self.blocks.block_grid(rows))
        bias[~self.blocks.finite[rows]] = 0.0
        return bias

    def pixels(self, pixels: NDArray) -> MultipathPotential:
        """The potential (n,) of flat pixel indices (n,)."""
        return self._at(self.blocks.pixel_coordinates(pixels), self.blocks.finite.ravel()[pixels])

    def _at(self, coordinates: tuple[NDArray, NDArray], finite: NDArray) -> MultipathPotential:
        coupling = self.blocks.to_pixels(self.coupling, coordinates)
        bias = self.blocks.to_pixels(self.bias_m, coordinates)
        with np.errstate(invalid="ignore", divide="ignore"):
            d_ab = np.where(coupling > 0, bias / np.where(coupling > 0, coupling, 1.0), np.nan)
        missing = ~finite
        coupling[missing], bias[missing], d_ab[missing] = 0.0, 0.0, np.nan
        return MultipathPotential(coupling, d_ab, bias, self.blocks.block_pixels)


@dataclass(frozen=True)
class EquivalentRhoAba:
    """The equivalent rho_ABA [1] and its d_AB [m] per block (Hb*Wb,) (:meth:`FacingBlocks.equivalent_rho_aba`),
    a correction model's geometric inputs; pixels interpolate them (:meth:`pixels`)."""

    blocks: FacingBlocks
    rho_aba: NDArray[np.float64]
    d_ab_m: NDArray[np.float64]

    def pixels(self, pixels: NDArray) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """rho_ABA (n,) and d_AB (n,) [m] of flat pixel indices (n,): 0 and NaN where no partner or no point.

        rho_ABA is interpolated as a coupling (:meth:`FacingBlocks.coupling_to_pixels`), d_AB linearly among
        the blocks with a partner.
        """
        coordinates = self.blocks.pixel_coordinates(pixels)
        rho_aba = self.blocks.coupling_to_pixels(self.rho_aba, coordinates)
        has = self.rho_aba > 0
        weight = self.blocks.to_pixels(has.astype(np.float64), coordinates)
        with np.errstate(invalid="ignore", divide="ignore"):
            d_ab = self.blocks.to_pixels(np.where(has, self.d_ab_m, 0.0), coordinates) / weight
        rho_aba[~self.blocks.finite.ravel()[pixels]] = 0.0
        return rho_aba, np.where(rho_aba > 0, d_ab, np.nan)


def facing_blocks(depth: NDArray, rays: NDArray | RayRowsLike, *, block_m: float = DEFAULT_BLOCK_M,
                  max_range_m: float = DEFAULT_MAX_RANGE_M, min_cos: float = DEFAULT_MIN_COS,
                  band_pixels: int = BAND_PIXELS) -> FacingBlocks:
    """Block planes of a range map (H, W) [m] along unit rays (H, W, 3) and the block pairs that face each other.

    This is the costly part of :func:`multipath_potential` (plane fits, the partner search); the footprint
    only scales the pairs' coupling, so one :class:`FacingBlocks` serves every footprint. The planes are
    fitted a tile of whole blocks at a time (about ``band_pixels``), each block from its own pixels, so the
    memory is that of one tile; ``rays`` may be anything that gives rows of rays by slicing
    (:class:`mpi_lidar.scans.scan.RayRows`), the depth any float array.
    """
    h, w = depth.shape
    b = block_size_pixels(depth, rays, block_m)
    bands = block_tiles(h, w, b, band_pixels)

    def band_planes(band: list[tuple[slice, slice]]) -> list[NDArray]:
        rows = band[0][0]
        halo_rows = slice(max(rows.start - 1, 0), min(rows.stop + 1, h))
        band_rays = np.asarray(rays[halo_rows], dtype=np.float64)
        with np.errstate(invalid="ignore", divide="ignore"):  # blocks without points (this thread only)
            tiles = [_tile_planes(depth, band_rays, halo_rows, rows, columns, b) for _, columns in band]
        return [np.concatenate(parts, axis=1) for parts in zip(*tiles, strict=True)]

    fitted = on_cores(band_planes, bands)
    centres, normals, keep, usable, rms, area, block_cos_i, finite = (np.concatenate(parts)
                                                                       for parts in zip(*fitted, strict=True))
    index = np.flatnonzero(usable.ravel())
    empty = np.zeros(0)
    pairs = FacingPairs(np.zeros(0, dtype=np.intp), np.zeros(0, dtype=np.intp), empty, empty, empty, empty, empty,
                        empty)
    if index.size >= 2:
        c, n = centres.reshape(-1, 3)[index], normals.reshape(-1, 3)[index]
        a_blk, cos_blk, noise = area.ravel()[index], block_cos_i.ravel()[index], rms.ravel()[index]
        found = pairs_within(c, max_range_m)
        if found.size:
            i, j = found[:, 0], found[:, 1]
            pairs = _facing_pairs(i, j, c, n, cos_blk, a_blk, noise[i] + noise[j], min_cos)
    return FacingBlocks((h, w), b, centres, normals, keep, usable, rms, index, pairs, finite)


def _tile_planes(depth: NDArray, band_rays: NDArray, halo_rows: slice, rows: slice, columns: slice, b: int
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
    solid_angle = _pixel_solid_angle(halo)[core]
    cos_i = np.abs(np.einsum("hwni,hwi->hwn", np.nan_to_num(to_blocks(r, b)), normals))
    pixel_area = to_blocks(d**2 * solid_angle, b) / np.maximum(cos_i, 0.1)
    area = np.where(keep, np.nan_to_num(pixel_area), 0.0).sum(-1)
    centre_ray = centres / np.maximum(np.linalg.norm(centres, axis=-1, keepdims=True), 1e-12)
    block_cos_i = np.maximum(-np.einsum("hwi,hwi->hw", normals, centre_ray), 1e-3)
    return centres, normals, keep, usable, rms, area, block_cos_i, np.isfinite(d)


def _pair_coupling(centre_a: NDArray, normal_a: NDArray, cos_i: NDArray, area_a: NDArray, centre_b: NDArray,
                   normal_b: NDArray, area_b: NDArray, noise_m: NDArray, footprint_area_m2: float, min_cos: float
                   ) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """kappa_B of block B at block A for pairs of fitted planes (P,), and their distance (P,) [m].

    The kernel is :func:`mpi_lidar.physics.coupling.footprint_coupling`; here a pair faces when both cosines
    exceed ``min_cos`` and each centre stands clear of the other's plane by more than three times
    ``noise_m`` (the two fits' summed residual RMS) [m]; r is clamped below by the larger block's side.
    Centres (P, 3) [m], unit normals (P, 3), incidence cosines at A (P,) and block areas (P,) [m^2].
    """
    dist, facing, r_eff, cos_a, cos_b = _pair_terms(centre_a, normal_a, area_a, centre_b, normal_b, area_b,
                                                    noise_m, min_cos)
    return np.where(facing, footprint_coupling(cos_a, cos_b, area_b, r_eff, cos_i, footprint_area_m2), 0.0), dist


def _pair_terms(centre_a: NDArray, normal_a: NDArray, area_a: NDArray, centre_b: NDArray, normal_b: NDArray,
                area_b: NDArray, noise_m: NDArray, min_cos: float) -> tuple[NDArray, ...]:
    """Distance, facing mask, clamped distance and the two cosines of block pairs (P,) (:func:`_pair_coupling`)."""
    dist, cos_a, cos_b = pair_geometry(centre_a, normal_a, centre_b, normal_b)
    # Each centre must stand clear of the other's plane by more than the fits' noise can explain.
    margin = 3.0 * noise_m
    facing = (cos_a > min_cos) & (cos_b > min_cos) & (cos_a * dist > margin) & (cos_b * dist > margin)
    r_eff = np.maximum(dist, np.sqrt(np.maximum(area_b, area_a)))
    return dist, facing, r_eff, cos_a, cos_b


def _facing_pairs(i: NDArray, j: NDArray, centres: NDArray, normals: NDArray, cos_i: NDArray, area: NDArray,
                  noise_m: NDArray, min_cos: float) -> FacingPairs:
    """Both orders (i, j) and (j, i) of the unordered pairs of usable blocks (i, j) that face each other:
    first every facing (i, j), then every (j, i).

    Facing is symmetric (the distance, the margin and the clamp are; the two cosines swap places), so the
    test runs once per unordered pair.
    """
    dist, facing, r_eff, cos_a, cos_b = _pair_terms(centres[i], normals[i], area[i], centres[j], normals[j],
                                                    area[j], noise_m, min_cos)
    keep = np.flatnonzero(facing)
    a, b = np.concatenate([i[keep], j[keep]]), np.concatenate([j[keep], i[keep]])
    cos_a, cos_b = cos_a[keep], cos_b[keep]
    return FacingPairs(a, b, np.concatenate([cos_a, cos_b]), np.concatenate([cos_b, cos_a]), area[b],
                       np.tile(r_eff[keep], 2), cos_i[a], np.tile(dist[keep], 2))


def _pixel_solid_angle(rays: NDArray) -> NDArray[np.float64]:
    """Solid angle per pixel (H, W) [sr] of a ray grid, from the cross product of neighbouring ray steps."""
    h, w = rays.shape[:2]
    du = np.gradient(rays, axis=1) if w > 1 else np.zeros_like(rays)
    dv = np.gradient(rays, axis=0) if h > 1 else np.zeros_like(rays)
    # |du x dv| written out: the same numbers as np.linalg.norm(np.cross(du, dv), axis=-1), at a tenth of the cost.
    cross = (du[..., 1] * dv[..., 2] - du[..., 2] * dv[..., 1], du[..., 2] * dv[..., 0] - du[..., 0] * dv[..., 2],
             du[..., 0] * dv[..., 1] - du[..., 1] * dv[..., 0])
    return vector_length(np.stack(cross, axis=-1))
