"""Which point-cloud files a corrected scan's outputs hold, and their writing."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from mpi_lidar.errors import MpiLidarError
from mpi_lidar.reporting.output_levels import OutputLevel, check_outputs
from mpi_lidar.scans.pointcloud import PointCloudFormat, write_point_cloud
from mpi_lidar.scans.scan import Scan

# Point-cloud files per format: the raw cloud as PLY beside the corrected one; LAS/LAZ hold the raw range as an
# extra dimension of the corrected cloud. Ordered as the formats are written and listed.
POINT_CLOUD_FILES: dict[PointCloudFormat, tuple[str, ...]] = {
    PointCloudFormat.PLY: ("raw.ply", "corrected.ply"),
    PointCloudFormat.LAS: ("corrected.las",),
    PointCloudFormat.LAZ: ("corrected.laz",),
}
# Written at level full unless ``point_clouds`` says otherwise.
FULL_POINT_CLOUDS = (PointCloudFormat.PLY, PointCloudFormat.LAS)


def point_cloud_formats(outputs: str, point_clouds: tuple[str, ...] | list[str] | None = None
                        ) -> tuple[PointCloudFormat, ...]:
    """The point-cloud formats a scan writes: ``point_clouds`` at any level (each once, in the order of
    :data:`POINT_CLOUD_FILES`), or by default :data:`FULL_POINT_CLOUDS` at level full and none below."""
    if point_clouds is None:
        return FULL_POINT_CLOUDS if check_outputs(outputs) == OutputLevel.FULL else ()
    unknown = sorted(set(point_clouds) - set(POINT_CLOUD_FILES))
    if unknown:
        raise MpiLidarError(f"unknown point cloud format {unknown[0]!r}; choose from {', '.join(POINT_CLOUD_FILES)}")
    return tuple(fmt for fmt in POINT_CLOUD_FILES if fmt in point_clouds)


def point_cloud_files(scan: Scan, outputs: str, point_clouds: tuple[str, ...] | list[str] | None = None) -> list[str]:
    """The point-cloud files a scan's outputs hold at level ``outputs`` (none for a scan without geometry)."""
    if scan.ray_directions is None and (scan.azimuth_rad is None or scan.elevation_rad is None):
        return []
    return [name for fmt in point_cloud_formats(outputs, point_clouds) for name in POINT_CLOUD_FILES[fmt]]


def write_point_clouds(directory: Path, formats: tuple[PointCloudFormat, ...], raw_points: np.ndarray,
                       corrected_points: np.ndarray, fields: dict[str, np.ndarray]) -> list[str]:
    """The point clouds of ``formats`` into ``directory``; returns the names of the files written."""
    written = []
    for fmt in formats:
        for name in POINT_CLOUD_FILES[fmt]:
            points = raw_points if name.startswith("raw.") else corrected_points
            write_point_cloud(directory / name, fmt, points, fields)
            written.append(name)
    return written
