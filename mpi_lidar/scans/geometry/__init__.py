"""Geometry from a scan: point clouds, surface normals, and where multipath can exist (point-cloud files:
:mod:`mpi_lidar.scans.pointcloud`).

The parts, each private: ``_points`` (points and normals of a range map), ``_blocks`` (the grid of pixel blocks),
``_planes`` (a robust plane per block), ``_pairs`` (the block pairs that face each other), ``_potential`` (the
multipath potential per block and at pixels), ``_facing`` (:func:`facing_blocks` and :func:`multipath_potential`,
which join them).
"""

from __future__ import annotations

from mpi_lidar.scans.geometry._blocks import (
    BAND_PIXELS,
    MAX_BLOCK_PIXELS,
    RayRowsLike,
    block_row_bands,
    block_size_pixels,
    block_tiles,
    finer_block_pixels,
    nanmedian_last,
    to_blocks,
)
from mpi_lidar.scans.geometry._facing import (
    DEFAULT_BLOCK_M,
    DEFAULT_MAX_RANGE_M,
    DEFAULT_MIN_COS,
    NO_COUPLING_ROOT,
    BlockPotential,
    EquivalentRhoAba,
    FacingBlocks,
    MultipathPotential,
    facing_blocks,
    multipath_potential,
)
from mpi_lidar.scans.geometry._pairs import FACING_SIGMAS, FacingPairs
from mpi_lidar.scans.geometry._planes import EDGE_JUMP_M, fit_block_planes, pixel_solid_angle, plane_uncertainty
from mpi_lidar.scans.geometry._points import point_cloud, surface_normals

__all__ = [
    "BAND_PIXELS", "DEFAULT_BLOCK_M", "DEFAULT_MAX_RANGE_M", "DEFAULT_MIN_COS", "EDGE_JUMP_M", "FACING_SIGMAS",
    "MAX_BLOCK_PIXELS", "NO_COUPLING_ROOT", "BlockPotential", "EquivalentRhoAba", "FacingBlocks", "FacingPairs",
    "MultipathPotential", "RayRowsLike", "block_row_bands", "block_size_pixels", "block_tiles", "facing_blocks",
    "finer_block_pixels", "fit_block_planes", "multipath_potential", "nanmedian_last", "pixel_solid_angle",
    "plane_uncertainty", "point_cloud", "surface_normals", "to_blocks",
]
