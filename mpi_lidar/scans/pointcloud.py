"""Point clouds for LiDAR tools: LAS 1.4 / LAZ (laspy) and binary PLY (plyfile), with named per-point fields.

Both writers take the points of a scan grid (H, W, 3) [m] and any number of per-pixel fields (H, W), e.g. those
of :func:`correction_fields`. A pixel whose point is not finite is left out; every point keeps its pixel's
``row`` and ``column`` (uint32), so a point can always be traced back to the scan grid. Files are written
atomically (built beside the target, then renamed), replacing a previous file. What each file holds, field by
field, and how viewers open it: docs/reference/point-clouds.md.

LAS: version 1.4, point format 6, x/y/z scaled to 0.1 mm; every field is an extra-bytes dimension of its own
dtype, with its unit in the description (31 characters at most). ``intensity`` holds the field
:data:`INTENSITY_FIELD` (the amplitude) scaled to 16 bits, 65,535 at the file's largest amplitude; the scale
is in that field's description and in the JSON record. Points marked ``withheld`` (an invalid pixel placed at
its raw range) carry the Withheld bit and classification 7 (low point, noise); the others classification 1
(unclassified). One variable-length record (user :data:`LAS_METADATA_USER_ID`, record
:data:`LAS_METADATA_RECORD_ID`) holds a JSON object: the generator, each field's description, the intensity
scale, what withheld means, and whatever ``metadata`` the caller adds (the flag codes, the scanner frame). The
header names mpi-lidar and its version as the generating software. LAZ (laspy's lazrs backend) is the same,
compressed, its chunks on
every core (:func:`mpi_lidar.threads.cores`).

PLY: binary little-endian, float32 ``x``, ``y``, ``z`` [m], optional uchar ``red``, ``green``, ``blue`` (what
Open3D reads as positions and colours) and one property ``scalar_<field>`` per field (CloudCompare loads
properties with the ``scalar_`` prefix as scalar fields named after the rest). PLY has no withheld bit: the
caller leaves invalid pixels out.
"""

from __future__ import annotations

import json
from collections.abc import Mapping
from enum import StrEnum
from importlib.metadata import PackageNotFoundError, version
from pathlib import Path

import numpy as np
from numpy.typing import NDArray
from plyfile import PlyData, PlyElement

from mpi_lidar.storage.atomic import atomic_path
from mpi_lidar.threads import cores


class PointCloudFormat(StrEnum):
    """A point-cloud file format: LAS 1.4, LAZ (compressed LAS) or binary PLY."""

    LAS = "las"
    LAZ = "laz"
    PLY = "ply"


POINT_CLOUD_FORMATS = tuple(fmt.value for fmt in PointCloudFormat)
LAS_SCALE_M = 1e-4  # 0.1 mm
LAS_DESCRIPTION_CHARS = 31  # an extra-bytes description is 32 bytes, NUL-terminated
# What each field of correction_fields() holds, with its unit (LAS extra-bytes descriptions: 31 characters).
FIELD_DESCRIPTIONS = {
    "raw_range_m": "raw range [m]",
    "corrected_range_m": "corrected range [m]",
    "correction_mm": "corrected - raw range [mm]",
    "flag": "mpi-lidar correction flag",
    "amplitude_v2": "amplitude [V^2]",
    "uncertainty_m": "corrected range 1-sigma [m]",
    "row": "pixel row of the scan grid",
    "column": "pixel column of the scan grid",
}
INTENSITY_FIELD = "amplitude_v2"  # the field LAS intensity is filled from
INTENSITY_MAX = 65535  # the largest amplitude of a file maps to this intensity
LAS_CLASS_UNCLASSIFIED = 1
LAS_CLASS_LOW_NOISE = 7  # ASPRS class 7, "low point (noise)": withheld points
LAS_METADATA_USER_ID = "mpi-lidar"
LAS_METADATA_RECORD_ID = 1
PLY_SCALAR_PREFIX = "scalar_"  # CloudCompare reads properties so named as scalar fields
_NUMERIC_KINDS = "biuf"
_RETURN_BITS = 0x11  # return 1 of 1 (LAS 1.4 point format 6: return number, bits 0-3; number of returns, 4-7)
_WITHHELD_BIT = 0x04  # LAS 1.4 point format 6 classification flags: synthetic 1, key point 2, withheld 4


def generator() -> str:
    """The generating software named in every file: ``mpi-lidar <version>``."""
    try:
        return f"mpi-lidar {version('mpi-lidar')}"
    except PackageNotFoundError:  # run from a checkout that was never installed
        return "mpi-lidar"


def correction_fields(raw_range_m: NDArray, corrected_range_m: NDArray, flags: NDArray,
                      amplitude_v2: NDArray, uncertainty_m: NDArray | None = None) -> dict[str, NDArray]:
    """The per-pixel fields of a corrected scan (each (H, W)): raw and corrected range [m], the applied
    correction [mm] (0 where nothing was changed, NaN where the pixel is invalid), the flag (uint8, the codes
    of :class:`mpi_lidar.correction.Flag`), the amplitude [V^2] and, when given, the corrected range's
    uncertainty (one standard deviation) [m]."""
    raw = np.asarray(raw_range_m, dtype=np.float32)
    corrected = np.asarray(corrected_range_m, dtype=np.float32)
    fields: dict[str, NDArray] = {
        "raw_range_m": raw,
        "corrected_range_m": corrected,
        "correction_mm": (1e3 * (corrected.astype(np.float64) - raw)).astype(np.float32),
        "flag": np.asarray(flags).astype(np.uint8),
        "amplitude_v2": np.asarray(amplitude_v2, dtype=np.float32),
    }
    if uncertainty_m is not None:
        fields["uncertainty_m"] = np.asarray(uncertainty_m, dtype=np.float32)
    return fields


def _points_and_fields(points: NDArray, fields: Mapping[str, NDArray]
                       ) -> tuple[NDArray[np.float64], dict[str, NDArray], NDArray[np.bool_]]:
    """The finite points (N, 3), per field their values (N,), with row and column (uint32) added, and which
    pixels (H * W,) they are."""
    grid = np.asarray(points, dtype=np.float64)
    if grid.ndim != 3 or grid.shape[-1] != 3:
        raise ValueError(f"points must have shape (H, W, 3), got {grid.shape}")
    h, w = grid.shape[:2]
    reserved = {"x", "y", "z", "row", "column"} & set(fields)
    if reserved:
        raise ValueError(f"field names {sorted(reserved)} are reserved for the coordinates and pixel indices")
    keep = np.isfinite(grid).all(axis=-1).reshape(-1)
    rows, columns = np.divmod(np.flatnonzero(keep).astype(np.uint32), np.uint32(max(w, 1)))
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
    kept["row"], kept["column"] = rows, columns
    return grid.reshape(-1, 3)[keep], kept, keep


def intensity_scale(amplitude: NDArray) -> float:
    """Amplitude per intensity count [unit of the amplitude]: the largest finite amplitude over
    :data:`INTENSITY_MAX` (1 where none is positive)."""
    values = np.asarray(amplitude)
    largest = float(np.nanmax(values, initial=0.0, where=np.isfinite(values))) if values.size else 0.0
    return largest / INTENSITY_MAX if largest > 0 else 1.0


def intensity_counts(amplitude: NDArray, scale: float) -> NDArray[np.uint16]:
    """``amplitude / scale`` rounded to uint16 counts (0 where not finite or negative)."""
    counts = np.rint(np.nan_to_num(np.asarray(amplitude, dtype=np.float64) / scale, nan=0.0, posinf=0.0,
                                   neginf=0.0))
    return np.clip(counts, 0, INTENSITY_MAX).astype(np.uint16)


def write_las(path: str | Path, points: NDArray, fields: Mapping[str, NDArray], compress: bool | None = None, *,
              withheld: NDArray | None = None, descriptions: Mapping[str, str] | None = None,
              metadata: Mapping[str, object] | None = None) -> Path:
    """Write a LAS 1.4 file (LAZ when ``compress``, by default when the suffix is ``.laz``).

    ``points`` (H, W, 3) [m], ``fields`` name -> (H, W) array; ``withheld`` (H, W) bool: the points marked
    Withheld, classification 7; ``descriptions`` field name -> description, over :data:`FIELD_DESCRIPTIONS`
    (cut to 31 characters in the extra bytes, whole in the JSON record); ``metadata``: more entries of the
    JSON record. See the module docstring.
    """
    import laspy  # here, not at the top: laspy takes 0.2 s to import, which a run without LAS files never pays

    path = Path(path)
    compress = path.suffix.lower() == ".laz" if compress is None else compress
    if withheld is not None and np.shape(withheld) != np.shape(points)[:2]:
        raise ValueError(f"withheld must have shape {np.shape(points)[:2]} like the points, got {np.shape(withheld)}")
    xyz, values, keep = _points_and_fields(points, fields)
    described = {**FIELD_DESCRIPTIONS, **(descriptions or {})}
    described = {name: described.get(name, name) for name in values}
    record: dict[str, object] = {"generator": generator(), "fields": described}
    if INTENSITY_FIELD in values:
        scale = intensity_scale(values[INTENSITY_FIELD])
        described[INTENSITY_FIELD] = f"{described[INTENSITY_FIELD]} = {scale:.2e} * I"
        record["intensity"] = {"field": INTENSITY_FIELD, "per_count": scale,
                               "meaning": f"{INTENSITY_FIELD} = intensity * per_count, intensity {INTENSITY_MAX} "
                                          "at the file's largest amplitude"}
    record["withheld"] = (f"withheld points (classification {LAS_CLASS_LOW_NOISE}, low point/noise) are invalid "
                          f"pixels placed at their raw range; the others have classification "
                          f"{LAS_CLASS_UNCLASSIFIED}")
    record.update(metadata or {})

    header = laspy.LasHeader(version="1.4", point_format=6)
    header.generating_software = generator()[:32]
    header.system_identifier = "OTHER"
    header.scales = np.full(3, LAS_SCALE_M)
    header.offsets = np.floor(xyz.min(axis=0)) if xyz.size else np.zeros(3)
    header.add_extra_dims([laspy.ExtraBytesParams(name=name, type=v.dtype,
                                                  description=described[name][:LAS_DESCRIPTION_CHARS])
                           for name, v in values.items()])
    header.vlrs.append(laspy.VLR(user_id=LAS_METADATA_USER_ID, record_id=LAS_METADATA_RECORD_ID,
                                 description="JSON metadata", record_data=json.dumps(record).encode()))
    # The packed records filled column by column: laspy's per-dimension setters copy and scale each one again.
    record_array = np.zeros(xyz.shape[0], dtype=header.point_format.dtype())
    for axis, name in enumerate("XYZ"):
        record_array[name] = np.rint((xyz[:, axis] - header.offsets[axis]) / LAS_SCALE_M)
    record_array["bit_fields"] = _RETURN_BITS
    if INTENSITY_FIELD in values:
        record_array["intensity"] = intensity_counts(values[INTENSITY_FIELD], scale)
    marked = np.zeros(xyz.shape[0], bool) if withheld is None else np.asarray(withheld, bool).reshape(-1)[keep]
    record_array["classification_flags"] = np.where(marked, _WITHHELD_BIT, 0)
    record_array["classification"] = np.where(marked, LAS_CLASS_LOW_NOISE, LAS_CLASS_UNCLASSIFIED)
    for name, v in values.items():
        record_array[name] = v
    las = laspy.LasData(header, points=laspy.PackedPointRecord(record_array, header.point_format))
    with atomic_path(path, replace=True, what="point cloud") as staging, staging.open("wb") as stream:
        backend = laspy.LazBackend.LazrsParallel if cores() > 1 else laspy.LazBackend.Lazrs
        las.write(stream, do_compress=compress, laz_backend=backend if compress else None)
    return path


def las_metadata(path: str | Path) -> dict[str, object]:
    """The JSON record of a LAS/LAZ file written by :func:`write_las` (empty if it has none)."""
    import laspy

    with laspy.open(path) as reader:
        for vlr in reader.header.vlrs:
            if vlr.user_id == LAS_METADATA_USER_ID and vlr.record_id == LAS_METADATA_RECORD_ID:
                return json.loads(bytes(vlr.record_data).decode())
    return {}


def write_ply(path: str | Path, points: NDArray, fields: Mapping[str, NDArray], colors: NDArray | None = None,
              comments: tuple[str, ...] = ()) -> Path:
    """Write a binary little-endian PLY: float32 x, y, z [m], uchar red, green, blue when ``colors`` (H, W, 3)
    uint8 are given, and one property ``scalar_<name>`` per field; ``comments`` go to the header after the
    generator's. ``points`` (H, W, 3) [m], ``fields`` name -> (H, W) array; see the module docstring.
    """
    path = Path(path)
    xyz, values, keep = _points_and_fields(points, fields)
    wide = sorted(name for name, v in values.items() if v.dtype.kind in "iu" and v.dtype.itemsize > 4)
    if wide:
        raise ValueError(f"fields {wide} are 64-bit integers, which PLY cannot hold; convert them to 32 bits")
    colour_names = ("red", "green", "blue") if colors is not None else ()
    if colors is not None:
        colors = np.asarray(colors)
        if colors.shape != (*np.shape(points)[:2], 3) or colors.dtype != np.uint8:
            raise ValueError(f"colors must be uint8 of shape {(*np.shape(points)[:2], 3)}, got {colors.dtype} "
                             f"{colors.shape}")
    records = np.empty(xyz.shape[0], dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4")]
                       + [(name, "u1") for name in colour_names]
                       + [(PLY_SCALAR_PREFIX + name, v.dtype.newbyteorder("<")) for name, v in values.items()])
    for axis, name in enumerate("xyz"):
        records[name] = xyz[:, axis]
    if colors is not None:
        kept_colours = colors.reshape(-1, 3)[keep]
        for channel, name in enumerate(colour_names):
            records[name] = kept_colours[:, channel]
    for name, v in values.items():
        records[PLY_SCALAR_PREFIX + name] = v
    data = PlyData([PlyElement.describe(records, "vertex")], text=False, byte_order="<",
                   comments=[f"generated by {generator()}", *comments])
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
