"""Albedo from amplitude: per block, per surface, and less the light the multipath adds.

A Lambertian surface at range d and incidence cosine cos_i returns the amplitude

(F3)  Gamma = Gamma_R rho cos_i / d^2 |1 + ratio|,

Gamma_R the sensor's amplitude of a white surface at 1 m [V^2 m^2] and |1 + ratio| the gain of the multipath
(:mod:`._coupling`, (F6)). A block's albedo is (F3) solved for rho with the gain taken as one; a surface's is
the median over its blocks with the least coupling, where that gain is smallest; the light-free albedo divides
each block's by the gain the model predicts at a footprint.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import NDArray

from mpi_lidar.config import SensorConfig
from mpi_lidar.correction.footprint._surfaces import ANCHOR_SHARE, pair_coupling
from mpi_lidar.scans.geometry import BAND_PIXELS, FacingBlocks, nanmedian_last, to_blocks
from mpi_lidar.scans.scan import Scan
from mpi_lidar.threads import on_cores

if TYPE_CHECKING:
    from mpi_lidar.correction.footprint._coupling import PlaneCoupling

# The albedos less the multipath's gain: fixed-point iterations at one footprint (the gain grows with them).
ALBEDO_ITERATIONS = 3


def block_albedo(scan: Scan, blocks: FacingBlocks, sensor: SensorConfig,
                 tile_pixels: int = BAND_PIXELS) -> NDArray[np.float64]:
    """Albedo per block (Hb*Wb,) from the amplitude of its inlier pixels: rho = Gamma d^2 / (Gamma_R cos_i), (F3)
    without the multipath's gain.

    Parameters
    ----------
    scan : Scan
        The scan (its maps may stay in the store).
    blocks : FacingBlocks
        Its blocks.
    sensor : SensorConfig
        The sensor (its ``gamma_r_v2``).
    tile_pixels : int
        Pixels per tile of whole blocks (:meth:`FacingBlocks.tiles`): the temporaries stay within one tile.

    Returns
    -------
    NDArray[np.float64]
        The median over each block's inliers of the amplitude (mean over frequencies) times d^2 over
        Gamma_R cos_i (cos_i at least 0.1), clipped to 0.01-1.5; 0 for blocks without a plane. [1]
    """
    rays = scan.ray_rows()
    assert rays is not None, "a scan with geometry"

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


def white_albedo(blocks: FacingBlocks) -> NDArray[np.float64]:
    """Albedo per block (Hb*Wb,) where the amplitudes cannot tell it: 1 (white) for every block with a plane, 0
    for the others (as :func:`block_albedo` has them)."""
    return blocks.usable.ravel().astype(np.float64)


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
    """The albedo per block (Hb*Wb,) that weighs each partner's multipath in the blocks' model inputs.

    Parameters
    ----------
    blocks : FacingBlocks
        The scan's blocks.
    measured : NDArray
        Their albedos (Hb*Wb,) (:func:`block_albedo`). [1]
    components : NDArray
        Their connected surfaces (Hb*Wb,) (:func:`surface_labels`).

    Returns
    -------
    NDArray[np.float64]
        Each connected surface's :func:`surface_albedo`, its far blocks picked by their pair coupling. [1]
    """
    return surface_albedo(measured, components, pair_coupling(blocks))


def surface_albedo(albedo: NDArray, components: NDArray, coupling: NDArray) -> NDArray[np.float64]:
    """One albedo per connected surface (Hb*Wb,): the median over its share ``ANCHOR_SHARE`` of blocks with the
    least ``coupling`` (Hb*Wb,).

    Multipath adds light ((F3): Gamma grows with |1 + ratio|), most near an edge, so a block's own amplitude
    overstates its albedo just where the partners that matter lie; the surface's far blocks do not. Blocks
    outside any surface keep their own estimate.
    """
    out = albedo.copy()
    for label in np.unique(components[components >= 0]):
        members = np.flatnonzero(components == label)
        far = members[coupling[members] <= np.quantile(coupling[members], ANCHOR_SHARE)]
        out[members] = np.median(albedo[far])
    return out


def light_free_albedo(plane: PlaneCoupling, measured: NDArray, components: NDArray, area_m2: float
                      ) -> NDArray[np.float64]:
    """The albedo per surface of the blocks' ``measured`` albedos (Hb*Wb,) divided by the gain the multipath gives
    them at footprint ``area_m2`` [m^2].

    The gain itself grows with the albedos: ``ALBEDO_ITERATIONS`` fixed-point steps of
    rho <- surface_albedo(measured / |1 + ratio(rho)|) (F3), each surface's far blocks picked by the coupling of
    the partner planes and curved partners at the block centres (:attr:`PlaneCoupling.coupling_at_blocks`).
    """
    coupling = plane.coupling_at_blocks
    albedo = surface_albedo(measured, components, coupling)
    for _ in range(ALBEDO_ITERATIONS if area_m2 > 0 else 0):
        albedo = surface_albedo(measured / plane.block_gain(area_m2, albedo), components, coupling)
    return albedo
