"""A scan's block planes and the block pairs that face each other: where multipath can exist."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from mpi_lidar.physics.coupling import DEFAULT_FOOTPRINT_AREA_M2
from mpi_lidar.scans.geometry._blocks import BAND_PIXELS, RayRowsLike, block_row_bands, block_size_pixels, block_tiles
from mpi_lidar.scans.geometry._pairs import FacingPairs, facing_pairs, pairs_within
from mpi_lidar.scans.geometry._planes import tile_planes
from mpi_lidar.threads import on_cores

# The effective receiver footprint A_fp [m^2] of the A -> B -> A coupling, 90 pi (12 mm)^2, is defined with
# its kernel in mpi_lidar.physics.coupling (DEFAULT_FOOTPRINT_AREA_M2, imported above).
DEFAULT_BLOCK_M = 0.03
DEFAULT_MAX_RANGE_M = 0.5
DEFAULT_MIN_COS = 0.1
# 1 / sqrt(coupling) [1] standing in for a block without coupling when coupling is interpolated.
NO_COUPLING_ROOT = 1e3


def multipath_potential(depth: NDArray, rays: NDArray, *, block_m: float = DEFAULT_BLOCK_M,
                        max_range_m: float = DEFAULT_MAX_RANGE_M,
                        footprint_area_m2: float = DEFAULT_FOOTPRINT_AREA_M2,
                        min_cos: float = DEFAULT_MIN_COS) -> MultipathPotential:
    """Where multipath can exist in a scan, from its range map (H, W) [m] and unit rays (H, W, 3).

    The scan is cut into square blocks of about ``block_m`` [m]; a robust plane per block (centre, normal,
    area) stands in for its surface, so the raw depth's noise and its own smooth multipath bias do not
    make fake partners. For each pair of blocks A, B closer than ``max_range_m`` [m] that face each other
    (cos_A, cos_B > ``min_cos``, each centre further from the other's plane than three times the two fits'
    residual RMS, and each cosine beyond three sds of the planes' turn under the noise, so noisy planes of one
    surface never face each other), B couples to A with
    the scene simulator's kappa_B = (cos_A cos_B)^2 dA_B A_fp / (pi^2 r^4 cos_i) (the one kernel of
    :mod:`mpi_lidar.physics.coupling`; r clamped below by the block size, the sum capped at 1). A plane, a
    convex surface or open sky has no facing pair: zero everywhere. Block values are interpolated bilinearly to pixels.
    Occlusion between A and B is ignored, and surfaces outside the scan's field of view are not known.
    Everything but the footprint is in :func:`facing_blocks`; this is ``facing_blocks(...).potential(A_fp)``.
    """
    return facing_blocks(depth, rays, block_m=block_m, max_range_m=max_range_m,
                         min_cos=min_cos).potential(footprint_area_m2)


@dataclass(frozen=True)
class FacingBlocks:
    """A scan's block planes and the block pairs that face each other: the potential up to the footprint.

    Block arrays are (Hb, Wb, ...) as :func:`fit_block_planes` returns them; ``index`` holds the flat
    indices of the usable blocks, in the order the pairs refer to; ``shape`` is the scan's (H, W),
    ``finite`` (H, W) marks the pixels with a point and ``normal_sd_rad`` (Hb, Wb) is the sd of each block's
    normal under the noise [rad] (:func:`~mpi_lidar.scans.geometry.plane_uncertainty`).
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
    normal_sd_rad: NDArray[np.float64]

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
        the edge blocks' values continued beyond them (``scipy.ndimage.map_coordinates``, order 1, mode
        "nearest")."""
        from scipy.ndimage import map_coordinates  # imported where used: the start-up does not pay for it

        hb, wb = self.usable.shape
        rows, columns = self.block_grid() if coordinates is None else coordinates
        grid = np.asarray(block_values, dtype=np.float64).reshape(hb, wb)
        return map_coordinates(grid, np.stack(np.broadcast_arrays(rows, columns)), order=1, mode="nearest")

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

    def block_potential(self, footprint_area_m2: float, albedo: NDArray | None = None) -> BlockPotential:
        """Coupling and bias per block for the receiver footprint A_fp [m^2]; pixels interpolate them.

        ``albedo`` (Hb*Wb,) [1]: each pair's coupling weighed by its partner block's albedo, the share of the
        light it sends back; None: white partners, the largest multipath the geometry allows (the gate's)."""
        hb, wb = self.usable.shape
        coupling_blocks = np.zeros(hb * wb)
        weighted_r = np.zeros(hb * wb)
        if self.pairs.a.size:
            kappa = self.pairs.kappa(footprint_area_m2)
            if albedo is not None:
                kappa = kappa * albedo[self.index[self.pairs.b]]
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


def facing_blocks(depth: NDArray, rays: NDArray | RayRowsLike, *, block_m: float = DEFAULT_BLOCK_M,
                  max_range_m: float = DEFAULT_MAX_RANGE_M, min_cos: float = DEFAULT_MIN_COS,
                  band_pixels: int = BAND_PIXELS, depth_sigma: NDArray | None = None,
                  block_pixels: int | None = None) -> FacingBlocks:
    """Block planes of a range map (H, W) [m] along unit rays (H, W, 3) and the block pairs that face each other.

    This is the costly part of :func:`multipath_potential` (plane fits, the partner search); the footprint
    only scales the pairs' coupling, so one :class:`FacingBlocks` serves every footprint. The planes are
    fitted a tile of whole blocks at a time (about ``band_pixels``), each block from its own pixels, so the
    memory is that of one tile; ``rays`` may be anything that gives rows of rays by slicing
    (:class:`mpi_lidar.scans.scan.RayRows`), the depth any float array.

    ``depth_sigma`` (H, W) [m] is the depth's sd per pixel under the scan's noise (NaN where not known; None:
    the planes' own residuals stand for it): a pair faces only where both planes turn towards each other
    beyond what that noise gives them (:func:`~mpi_lidar.scans.geometry.plane_uncertainty`), so the noisy
    planes of a flat surface never face each other at any range.

    ``block_pixels`` sets the blocks' side [px] (None: :func:`~mpi_lidar.scans.geometry.block_size_pixels`, about
    ``block_m``).
    """
    h, w = depth.shape
    b = block_pixels or block_size_pixels(depth, rays, block_m)
    bands = block_tiles(h, w, b, band_pixels)

    def band_planes(band: list[tuple[slice, slice]]) -> list[NDArray]:
        rows = band[0][0]
        halo_rows = slice(max(rows.start - 1, 0), min(rows.stop + 1, h))
        band_rays = np.asarray(rays[halo_rows], dtype=np.float64)
        with np.errstate(invalid="ignore", divide="ignore"):  # blocks without points (this thread only)
            tiles = [tile_planes(depth, band_rays, halo_rows, rows, columns, b, depth_sigma) for _, columns in band]
        return [np.concatenate(parts, axis=1) for parts in zip(*tiles, strict=True)]

    fitted = on_cores(band_planes, bands)
    centres, normals, keep, usable, rms, area, block_cos_i, normal_sd, centre_sd, finite = (
        np.concatenate(parts) for parts in zip(*fitted, strict=True))
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
            pairs = facing_pairs(i, j, c, n, cos_blk, a_blk, noise[i] + noise[j], min_cos,
                                 normal_sd.ravel()[index], centre_sd.ravel()[index])
    return FacingBlocks((h, w), b, centres, normals, keep, usable, rms, index, pairs, finite, normal_sd)


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
