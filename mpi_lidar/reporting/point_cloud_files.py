"""Which point-cloud files a corrected scan's outputs hold, what they record, and their writing.

The corrected cloud as LAS/LAZ keeps every pixel with a finite raw range: a valid pixel at its corrected
range, an invalid one (flags 2-5) at its raw range, marked Withheld and classification 7 (noise). Its JSON
record carries the flag codes (:data:`FLAG_MEANINGS`) and the scanner frame (:data:`SCANNER_FRAME`). The PLY
files (``raw.ply``, ``corrected.ply``) hold the valid pixels only, coloured by amplitude (corrected pixels in
amber). Every file: docs/reference/point-clouds.md.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from mpi_lidar.correction.options import INVALID_FLAGS, Flag
from mpi_lidar.errors import MpiLidarError
from mpi_lidar.reporting.output_levels import OutputLevel, check_outputs
from mpi_lidar.scans.geometry import point_cloud
from mpi_lidar.scans.pointcloud import (
    LAS_DESCRIPTION_CHARS,
    LasBand,
    PointCloudFormat,
    correction_fields,
    intensity_scale,
    write_las_bands,
    write_ply,
)
from mpi_lidar.scans.scan import RayRows, Scan

# Point-cloud files per format: the raw cloud as PLY beside the corrected one; LAS/LAZ hold the raw range as an
# extra dimension of the corrected cloud. Ordered as the formats are written and listed.
POINT_CLOUD_FILES: dict[PointCloudFormat, tuple[str, ...]] = {
    PointCloudFormat.PLY: ("raw.ply", "corrected.ply"),
    PointCloudFormat.LAS: ("corrected.las",),
    PointCloudFormat.LAZ: ("corrected.laz",),
}
# Written at level full unless ``point_clouds`` says otherwise: the LAZ and the raw and corrected PLY files.
FULL_POINT_CLOUDS = (PointCloudFormat.PLY, PointCloudFormat.LAZ)
# The formats each level writes by default. The default level (light) writes the LAZ: it costs 15-20 % of a
# megapixel scan's correction (docs/results/point-clouds.md), within the 20 % the default outputs may add.
LEVEL_POINT_CLOUDS: dict[OutputLevel, tuple[PointCloudFormat, ...]] = {
    OutputLevel.FULL: FULL_POINT_CLOUDS,
    OutputLevel.LIGHT: (PointCloudFormat.LAZ,),
    OutputLevel.DATA: (),
}
# One letter per flag code, for the 31 characters of the LAS ``flag`` description ("0C 1N 2F ...").
FLAG_LETTERS = {
    Flag.CORRECTED: "C", Flag.NOT_NEEDED: "N", Flag.NOT_FINITE: "F", Flag.NO_RETURN: "R", Flag.SATURATED: "S",
    Flag.INCONSISTENT: "I", Flag.OUT_OF_RANGE: "O", Flag.NO_MULTIPATH: "M", Flag.UNCALIBRATED: "U",
    Flag.AMBIGUOUS: "A",
}
# What each flag code means (docs/reference/flags.md says more), as the JSON record carries it.
FLAG_MEANINGS = {
    Flag.CORRECTED: "valid, corrected by the model",
    Flag.NOT_NEEDED: "valid, skipped by a pixel-wise gate; raw range kept",
    Flag.NOT_FINITE: "invalid: a NaN or infinite depth or amplitude",
    Flag.NO_RETURN: "invalid: amplitude below the no-light noise",
    Flag.SATURATED: "invalid: amplitude above saturation",
    Flag.INCONSISTENT: "invalid: the frequencies' depths disagree",
    Flag.OUT_OF_RANGE: "valid, outside the model's range; measured range kept",
    Flag.NO_MULTIPATH: "valid, no facing surface causes multipath; raw range kept",
    Flag.UNCALIBRATED: "valid, footprint estimate not significant; raw range kept",
    Flag.AMBIGUOUS: "wrap counts ambiguous; range as measured (wrapped)",
}
# How x, y, z follow from a pixel's azimuth and elevation (mpi_lidar.scans.scan.grid_rays).
SCANNER_FRAME = {
    "origin": "the scanner's optical centre",
    "units": "m",
    "x": "cos(elevation) * sin(azimuth) * range",
    "y": "sin(elevation) * range",
    "z": "cos(elevation) * cos(azimuth) * range",
    "handedness": "right-handed: +z is the ray at azimuth 0 and elevation 0, elevation turns towards +y, azimuth "
                  "turns from +z towards +x (counter-clockwise seen from +y)",
    "row": "index of the scan's elevation_rad (or of its ray_directions' first axis)",
    "column": "index of the scan's azimuth_rad (or of its ray_directions' second axis)",
    "rays": "a scan stored with ray_directions uses those unit vectors as they are",
}
CORRECTED_RGB = np.array([1.0, 0.62, 0.15])  # amber, times the amplitude's grey level
_PERCENTILE_SAMPLE = 100_000  # amplitudes the colour scale's 99th percentile is taken on


def flag_description() -> str:
    """The LAS ``flag`` description: each code with its letter of :data:`FLAG_LETTERS` ("0C 1N 2F ..."),
    without spaces if they do not fit 31 characters."""
    spaced = " ".join(f"{int(flag)}{FLAG_LETTERS[flag]}" for flag in Flag)
    return spaced if len(spaced) <= LAS_DESCRIPTION_CHARS else spaced.replace(" ", "")


def point_cloud_metadata() -> dict[str, object]:
    """What the LAS/LAZ JSON record adds to the writer's own: the flag codes and the scanner frame."""
    return {
        "flags": {str(int(flag)): {"name": flag.name.lower(), "letter": FLAG_LETTERS[flag],
                                   "meaning": FLAG_MEANINGS[flag], "invalid": flag in INVALID_FLAGS}
                  for flag in Flag},
        "frame": SCANNER_FRAME,
    }


def point_cloud_colors(flags: NDArray, amplitude: NDArray) -> NDArray[np.uint8]:
    """Colours (H, W, 3) uint8: the amplitude's grey level (square root of its share of the 99th percentile,
    from 40 to 255), amber where the pixel was corrected."""
    values = np.asarray(amplitude, dtype=np.float32)
    finite = values[np.isfinite(values)]
    finite = finite[:: max(1, finite.size // _PERCENTILE_SAMPLE)]
    top = float(np.percentile(finite, 99)) if finite.size else 0.0
    share = np.clip(np.nan_to_num(values / top if top > 0 else np.ones_like(values), nan=0.0), 0.0, 1.0)
    grey = (40 + 215 * np.sqrt(share)).astype(np.float32)
    rgb = np.repeat(grey[..., None], 3, axis=-1)
    corrected = np.asarray(flags) == Flag.CORRECTED
    rgb[corrected] *= CORRECTED_RGB.astype(np.float32)
    return np.rint(rgb).astype(np.uint8)


def point_cloud_formats(outputs: str, point_clouds: tuple[str, ...] | list[str] | None = None
                        ) -> tuple[PointCloudFormat, ...]:
    """The point-cloud formats a scan writes: ``point_clouds`` at any level (each once, in the order of
    :data:`POINT_CLOUD_FILES`), or by default the level's :data:`LEVEL_POINT_CLOUDS` (PLY and LAZ at level
    full, LAZ at light, none at data)."""
    if point_clouds is None:
        return LEVEL_POINT_CLOUDS[check_outputs(outputs)]
    unknown = sorted(set(point_clouds) - set(POINT_CLOUD_FILES))
    if unknown:
        raise MpiLidarError(f"unknown point cloud format {unknown[0]!r}; choose from {', '.join(POINT_CLOUD_FILES)}")
    return tuple(fmt for fmt in POINT_CLOUD_FILES if fmt in point_clouds)


def point_cloud_files(scan: Scan, outputs: str, point_clouds: tuple[str, ...] | list[str] | None = None) -> list[str]:
    """The point-cloud files a scan's outputs hold at level ``outputs`` (none for a scan without geometry)."""
    if scan.ray_directions is None and (scan.azimuth_rad is None or scan.elevation_rad is None):
        return []
    return [name for fmt in point_cloud_formats(outputs, point_clouds) for name in POINT_CLOUD_FILES[fmt]]


def write_point_clouds(directory: Path, formats: tuple[PointCloudFormat, ...], rays: NDArray | RayRows,
                       measured_depth: NDArray, corrected_depth: NDArray, flags: NDArray, amplitude_v2: NDArray,
                       uncertainty_m: NDArray | None = None) -> list[str]:
    """The point clouds of ``formats`` into ``directory``; returns the names of the files written.

    ``rays`` (H, W, 3) unit rays, or a :class:`~mpi_lidar.scans.scan.RayRows` where no PLY is written (the LAS
    and LAZ files are built a band of rows at a time, the PLY files whole); ``measured_depth`` the highest
    frequency's measured (unwrapped) range and ``corrected_depth`` the corrected range (NaN where invalid) [m];
    ``flags`` the pixel flags; ``amplitude_v2`` the highest frequency's amplitude [V^2]; ``uncertainty_m`` the
    corrected range's uncertainty [m], an extra
    field where given. Each file's fields are those of :func:`~mpi_lidar.scans.pointcloud.correction_fields`.
    """
    if not formats:
        return []
    written = []
    if PointCloudFormat.PLY in formats:
        fields = correction_fields(measured_depth, corrected_depth, flags, amplitude_v2, uncertainty_m)
        valid = np.isfinite(fields["corrected_range_m"])
        whole_rays = rays[:]  # a RayRows builds every row
        colors = point_cloud_colors(fields["flag"], fields["amplitude_v2"])
        comments = (f"scalar_flag codes: {flag_description()} (docs/reference/point-clouds.md)",)
        for name, depth in zip(POINT_CLOUD_FILES[PointCloudFormat.PLY],
                               (np.where(valid, fields["raw_range_m"], np.nan), fields["corrected_range_m"]),
                               strict=True):
            write_ply(directory / name, point_cloud(depth, whole_rays), fields, colors, comments)
            written.append(name)
    las_formats = [fmt for fmt in (PointCloudFormat.LAS, PointCloudFormat.LAZ) if fmt in formats]
    if las_formats:
        band = _las_band(rays, measured_depth, corrected_depth, flags, amplitude_v2, uncertainty_m)
        # Every pixel with a finite raw or corrected range has a point (rays are finite).
        placed = np.isfinite(corrected_depth) | np.isfinite(measured_depth)
        per_count = intensity_scale(np.where(placed, amplitude_v2, np.nan))
        for fmt in las_formats:
            (name,) = POINT_CLOUD_FILES[fmt]
            write_las_bands(directory / name, np.shape(flags), band, per_count, compress=fmt == PointCloudFormat.LAZ,
                            descriptions={"flag": flag_description()}, metadata=point_cloud_metadata())
            written.append(name)
    return [name for fmt in formats for name in POINT_CLOUD_FILES[fmt] if name in written]


def _las_band(rays: NDArray | RayRows, measured_depth: NDArray, corrected_depth: NDArray, flags: NDArray,
              amplitude_v2: NDArray, uncertainty_m: NDArray | None) -> Callable[[slice], LasBand]:
    """The LAS/LAZ file's points a band of rows at a time: a valid pixel at its corrected range, an invalid one
    with a finite raw range at its raw range, withheld."""

    def band(rows: slice) -> LasBand:
        fields = correction_fields(measured_depth[rows], corrected_depth[rows], flags[rows], amplitude_v2[rows],
                                   None if uncertainty_m is None else uncertainty_m[rows])
        valid = np.isfinite(fields["corrected_range_m"])
        withheld = ~valid & np.isfinite(fields["raw_range_m"])
        points = point_cloud(np.where(valid, fields["corrected_range_m"], fields["raw_range_m"]), rays[rows])
        return points, fields, withheld

    return band
