"""Point clouds for LiDAR tools: LAS 1.4 / LAZ (laspy) and binary PLY (plyfile), with named per-point fields.

Both writers take the points of a scan grid (H, W, 3) [m] and any number of per-pixel fields (H, W), e.g. those
of :func:`correction_fields`. A pixel whose point is not finite (an invalid pixel) is left out; every point
keeps its pixel's ``row`` and ``column`` (uint32), so a point can always be traced back to the scan grid.
Files are written atomically (built beside the target, then renamed), replacing a previous file.

LAS: version 1.4, point format 6, x/y/z scaled to 0.1 mm; every field is an extra-bytes dimension of its own
dtype, with its unit in the description. LAZ (laspy's lazrs backend) is the same, compressed.
"""

from __future__ import annotations

from collections.abc import Mapping
from enum import StrEnum
from pathlib import Path

import laspy
import numpy as np
from numpy.typing import NDArray
from plyfile import PlyData, PlyElement

from mpi_lidar.storage.atomic import atomic_path


class PointCloudFormat(StrEnum):
    """A point-cloud file format: LAS 1.4, LAZ (compressed LAS) or binary PLY."""

    LAS = "las"
    LAZ = "laz"
    PLY = "ply"


POINT_CLOUD_FORMATS = tuple(fmt.value for fmt in PointCloudFormat)
LAS_SCALE_M = 1e-4  # 0.1 mm
# What each field of correction_fields() holds, with its unit (LAS extra-bytes descriptions: 31 characters).
FIELD_DESCRIPTIONS = {
    "raw_range_m": "raw range [m]",
    "corrected_range_m": "corrected range [m]",
    "correction_mm": "corrected - raw range [mm]",
    "flag": "mpi-lidar correction flag",
    "amplitude_v2": "amplitude [V^2]",
    "row": "pixel row of the scan grid",
    "column": "pixel column of the scan grid",
}
_NUMERIC_KINDS = "biuf"


def correction_fields(raw_range_m: NDArray, corrected_range_m: NDArray, flags: NDArray,
                      amplitude_v2: NDArray) -> dict[str, NDArray]:
    """The per-pixel fields of a corrected scan (each (H, W)): raw and corrected range [m], the applied
    correction [mm] (0 where nothing was changed, NaN where the pixel is invalid), the flag (uint8, the codes
    of :class:`mpi_lidar.correction.Flag`) and the amplitude [V^2]."""
    raw = np.asarray(raw_range_m, dtype=np.float32)
    corrected = np.asarray(corrected_range_m, dtype=np.float32)
    return {
        "raw_range_m": raw,
        "corrected_range_m": corrected,
        "correction_mm": (1e3 * (corrected.astype(np.float64) - raw)).astype(np.float32),
        "flag": np.asarray(flags).astype(np.uint8),
        "amplitude_v2": np.asarray(amplitude_v2, dtype=np.float32),
    }


def _points_and_fields(points: NDArray, fields: Mapping[str, NDArray]
                       ) -> tuple[NDArray[np.float64], dict[str, NDArray]]:
    """The finite points (N, 3) and, per field, their values (N,), with row and column (uint32) added."""
    grid = np.asarray(points, dtype=np.float64)
    if grid.ndim != 3 or grid.shape[-1] != 3:
        raise ValueError(f"points must have shape (H, W, 3), got {grid.shape}")
    h, w = grid.shape[:2]
    reserved = {"x", "y", "z", "row", "column"} & set(fields)
    if reserved:
        raise ValueError(f"field names {sorted(reserved)} are reserved for the coordinates and pixel indices")
    keep = np.isfinite(grid).all(axis=-1).reshape(-1)
    rows, columns = np.divmod(np.arange(h * w, dtype=np.uint32)[keep], np.uint32(w))
    kept = {}
    for name, values in fields.items():
        values = np.asarray(values)
        if values.shape != (h, w):
            raise ValueError(f"field {name!r} must have shape {(h, w)} like the points, got {values.shape}")
        if values.dtype == np.bool_:
            values = values.astype(np.uint8)
        elif values.dtype == np.float16:
            values = values.astype(np.float32)
        if values.dtype.kind not in _NUMERIC_KINDS:
            raise ValueError(f"field {name!r} must be numeric, got {values.dtype}")
        kept[name] = values.reshape(-1)[keep]
    kept["row"], kept["column"] = rows.astype(np.uint32), columns.astype(np.uint32)
    return grid.reshape(-1, 3)[keep], kept


def write_las(path: str | Path, points: NDArray, fields: Mapping[str, NDArray],
              compress: bool | None = None) -> Path:
    """Write a LAS 1.4 file (LAZ when ``compress``, by default when the suffix is ``.laz``).

    ``points`` (H, W, 3) [m], ``fields`` name -> (H, W) array; see the module docstring.
    """
    path = Path(path)
    compress = path.suffix.lower() == ".laz" if compress is None else compress
    xyz, values = _points_and_fields(points, fields)
    header = laspy.LasHeader(version="1.4", point_format=6)
    header.scales = np.full(3, LAS_SCALE_M)
    header.offsets = np.floor(xyz.min(axis=0)) if xyz.size else np.zeros(3)
    header.add_extra_dims([laspy.ExtraBytesParams(name=name, type=v.dtype,
                                                  description=FIELD_DESCRIPTIONS.get(name, name)[:31])
                           for name, v in values.items()])
    las = laspy.LasData(header)
    las.x, las.y, las.z = xyz[:, 0], xyz[:, 1], xyz[:, 2]
    for name, v in values.items():
        las[name] = v
    with atomic_path(path, replace=True, what="point cloud") as staging, staging.open("wb") as stream:
        las.write(stream, do_compress=compress, laz_backend=laspy.LazBackend.Lazrs if compress else None)
    return path


def write_ply(path: str | Path, points: NDArray, fields: Mapping[str, NDArray]) -> Path:
    """Write a binary little-endian PLY: float32 x, y, z [m] and one named property per field.

    ``points`` (H, W, 3) [m], ``fields`` name -> (H, W) array; see the module docstring.
    """
    path = Path(path)
    xyz, values = _points_and_fields(points, fields)
    wide = sorted(name for name, v in values.items() if v.dtype.kind in "iu" and v.dtype.itemsize > 4)
    if wide:
        raise ValueError(f"fields {wide} are 64-bit integers, which PLY cannot hold; convert them to 32 bits")
    records = np.empty(xyz.shape[0], dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4")]
                       + [(name, v.dtype.newbyteorder("<")) for name, v in values.items()])
    for axis, name in enumerate("xyz"):
        records[name] = xyz[:, axis]
    for name, v in values.items():
        records[name] = v
    data = PlyData([PlyElement.describe(records, "vertex")], text=False, byte_order="<")
    with atomic_path(path, replace=True, what="point cloud") as staging, staging.open("wb") as stream:
        data.write(stream)
    return path


def write_point_cloud(path: str | Path, fmt: str, points: NDArray, fields: Mapping[str, NDArray]) -> Path:
    """Write a point cloud in one of :data:`POINT_CLOUD_FORMATS` (``las``, ``laz`` or ``ply``)."""
    if fmt == "ply":
        return write_ply(path, points, fields)
    if fmt in ("las", "laz"):
        return write_las(path, points, fields, compress=fmt == "laz")
    raise ValueError(f"unknown point cloud format {fmt!r}; choose from {', '.join(POINT_CLOUD_FORMATS)}")
