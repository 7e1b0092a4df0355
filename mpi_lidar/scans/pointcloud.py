"""Point clouds for LiDAR tools: LAS 1.4 / LAZ (laspy) and binary PLY (plyfile), with named per-point fields.

Both writers take the points of a scan grid (H, W, 3) [m] and any number of per-pixel fields (H, W), e.g. those
of :func:`correction_fields`. A pixel whose point is not finite is left out; every point keeps its pixel's
``row`` and ``column`` (uint32), so a point can always be traced back to the scan grid. Files are written
atomically (built beside the target, then renamed), replacing a previous file. What each file holds, field by
field, and how viewers open it: docs/reference/point-clouds.md.

LAS: version 1.4, point format 6, x/y/z scaled to 0.1 mm; every field is an extra-bytes dimension of its own dtype,
with its unit in the description (31 characters at most). ``intensity`` holds the field :data:`INTENSITY_FIELD` (the
amplitude [V^2]) on one fixed scale, :data:`INTENSITY_PER_COUNT_V2` per count, the same in every file (so
intensities compare across an archive); the scale is in that field's description and in the JSON record. Points
marked ``withheld`` (an invalid pixel) carry the Withheld bit and classification 7 (low point, noise); the others
classification 1 (unclassified). The header's bounds are those of the points written. Every point is return
1 of 1, unless the fields :data:`RETURN_FIELDS` give its return number and number of returns (a pixel's second
return, written with :func:`write_las_bands`'s ``second``, is its own point); the header counts points by return.
One variable-length record (user
:data:`LAS_METADATA_USER_ID`, record :data:`LAS_METADATA_RECORD_ID`) holds a JSON object: the generator, each field's
description, the intensity scale, what withheld means, and whatever ``metadata`` the caller adds (the flag codes,
the scanner frame). The header names mpi-lidar and its version as the generating software. LAZ (laspy's lazrs
backend) is the same, compressed, its chunks on every core (:func:`mpi_lidar.threads.cores`).

PLY: binary little-endian, float32 ``x``, ``y``, ``z`` [m], optional uchar ``red``, ``green``, ``blue`` (what
Open3D reads as positions and colours) and one property ``scalar_<field>`` per field (CloudCompare loads
properties with the ``scalar_`` prefix as scalar fields named after the rest); second returns are vertices of
their own after the first returns'. PLY has no withheld bit: the caller leaves invalid pixels out.
"""

from __future__ import annotations

import json
from collections.abc import Callable, Mapping
from contextlib import ExitStack
from enum import StrEnum
from importlib.metadata import PackageNotFoundError, version
from pathlib import Path
from typing import Any

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
    "return_share": "return's share of the light [1]",
    "row": "pixel row of the scan grid",
    "column": "pixel column of the scan grid",
}
INTENSITY_FIELD = "amplitude_v2"  # the field LAS intensity is filled from
INTENSITY_MAX = 65535
# Amplitude per intensity count [V^2]: one scale for every file, so that intensities compare across scans and an
# archive. 65,535 counts are 0.655 V^2, about the default saturation (0.7176 V^2); a 2 m wall's 0.03 V^2 is 3,000.
INTENSITY_PER_COUNT_V2 = 1e-5
LAS_CLASS_UNCLASSIFIED = 1
LAS_CLASS_LOW_NOISE = 7  # ASPRS class 7, "low point (noise)": withheld points
LAS_METADATA_USER_ID = "mpi-lidar"
LAS_METADATA_RECORD_ID = 1
PLY_SCALAR_PREFIX = "scalar_"  # CloudCompare reads properties so named as scalar fields
_NUMERIC_KINDS = "biuf"
_RETURN_BITS = 0x11  # return 1 of 1 (LAS 1.4 point format 6: return number, bits 0-3; number of returns, 4-7)
# Fields a LAS/LAZ file holds in each point's return bits, not as extra bytes (a PLY holds them as properties):
# where a band has them, every point's return number and number of returns are theirs (uint8, 1-15).
RETURN_FIELDS = ("return_number", "number_of_returns")
_WITHHELD_BIT = 0x04  # LAS 1.4 point format 6 classification flags: synthetic 1, key point 2, withheld 4
# Pixels of the scan grid a LAS file is built from at a time: a band's points, fields and records take about
# 100 MB, whatever the scan's size (a 4000 x 4000 scan built whole took 2.5 GB more).
LAS_BAND_PIXELS = 1 << 20
# One band of a scan's rows for a LAS file: points (h, W, 3) [m], fields name -> (h, W), withheld (h, W) or None.
LasBand = tuple[NDArray, Mapping[str, NDArray], NDArray | None]
# A further return of some pixels, for a PLY file: points (H, W, 3) [m] (not finite where a pixel has none) and
# the same fields as the first returns'.
PlyReturns = tuple[NDArray, Mapping[str, NDArray]]


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


def _points_and_fields(points: NDArray, fields: Mapping[str, NDArray], first_row: int = 0
                       ) -> tuple[NDArray[np.float64], dict[str, NDArray], NDArray[np.bool_]]:
    """The finite points (N, 3), per field their values (N,), with row and column (uint32, rows counted from
    ``first_row``: the points may be a band of a scan's rows) added, and which pixels (H * W,) they are."""
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
    kept["row"], kept["column"] = rows + np.uint32(first_row), columns
    return grid.reshape(-1, 3)[keep], kept, keep


class PointCloudFrame(StrEnum):
    """The axes of a point cloud's coordinates. ``scanner``: the scan frame (x to the scanner's left, y up, z
    forward: :func:`mpi_lidar.scans.scan.grid_rays`); ``z-up``: x forward, y to the left, z up, as most point-cloud
    viewers and robotics tools (ROS REP 103) expect. Both right-handed, the scanner at the origin."""

    SCANNER = "scanner"
    Z_UP = "z-up"


# Which scanner-frame axis each axis of a frame is: z-up's x is the scanner's z (forward), and so on.
_FRAME_AXES = {PointCloudFrame.SCANNER: (0, 1, 2), PointCloudFrame.Z_UP: (2, 0, 1)}


def in_frame(points: NDArray, frame: str = PointCloudFrame.SCANNER) -> NDArray:
    """``points`` (..., 3) of the scanner frame in ``frame`` (:class:`PointCloudFrame`): a cyclic permutation of the
    axes, so lengths and handedness are kept. [m]"""
    axes = _FRAME_AXES[PointCloudFrame(frame)]
    return points if axes == (0, 1, 2) else points[..., list(axes)]


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
    JSON record. See the module docstring; :func:`write_las_bands` writes a scan a band of rows at a time.
    """
    grid = np.asarray(points)
    if withheld is not None and np.shape(withheld) != grid.shape[:2]:
        raise ValueError(f"withheld must have shape {grid.shape[:2]} like the points, got {np.shape(withheld)}")
    # The points' shape, the fields' names and kinds, checked on no rows (nothing copied), then the fields' shapes.
    _points_and_fields(grid[:0], {name: np.asarray(values)[:0] for name, values in fields.items()})
    wrong = [name for name, values in fields.items() if np.shape(values) != grid.shape[:2]]
    if wrong:
        raise ValueError(f"field {wrong[0]!r} must have shape {grid.shape[:2]} like the points, got "
                         f"{np.shape(fields[wrong[0]])}")
    def band(rows: slice) -> LasBand:
        marked = None if withheld is None else np.asarray(withheld)[rows]
        return grid[rows], {name: np.asarray(values)[rows] for name, values in fields.items()}, marked

    return write_las_bands(path, grid.shape[:2], band, INTENSITY_PER_COUNT_V2, compress, descriptions=descriptions,
                           metadata=metadata)


def write_las_bands(path: str | Path, shape: tuple[int, ...], band: Callable[[slice], LasBand],
                    intensity_per_count: float = INTENSITY_PER_COUNT_V2, compress: bool | None = None, *,
                    descriptions: Mapping[str, str] | None = None,
                    metadata: Mapping[str, object] | None = None,
                    second: Callable[[slice], LasBand] | None = None) -> Path:
    """Write a LAS 1.4 file (LAZ when ``compress``, by default when the suffix is ``.laz``) of a scan grid of
    ``shape`` (H, W), a band of rows at a time, so that memory stays that of a band of :data:`LAS_BAND_PIXELS`
    pixels whatever the scan's size: ``band(rows)`` gives those rows' points, fields and withheld marks
    (:data:`LasBand`), the same fields in every band. ``intensity_per_count``: the :data:`INTENSITY_FIELD` value
    of one intensity count (:data:`INTENSITY_PER_COUNT_V2`). The header's bounds are the written points'.
    Coordinates are stored in :data:`LAS_SCALE_M` steps from the scanner at the origin (int32: 214 km either
    way). ``descriptions`` and ``metadata`` as :func:`write_las` takes them. ``second(rows)``: those rows'
    second returns (points not finite where a pixel has none, the same fields), written after each band's points;
    the fields :data:`RETURN_FIELDS`, where given, fill each point's return bits, and the header counts the points
    by return.
    """
    import laspy  # here, not at the top: laspy takes 0.2 s to import, which a run without LAS files never pays

    path = Path(path)
    compress = path.suffix.lower() == ".laz" if compress is None else compress
    backend = laspy.LazBackend.LazrsParallel if cores() > 1 else laspy.LazBackend.Lazrs
    with atomic_path(path, replace=True, what="point cloud") as staging, staging.open("wb") as stream, \
            ExitStack() as open_writer:
        writer = None
        for rows in _row_bands(shape[0], shape[1]):
            for layer in (band,) if second is None else (band, second):
                points, fields, withheld = layer(rows)
                xyz, values, keep = _points_and_fields(points, fields, rows.start)
                if writer is None:  # the header needs the fields' types: those of the first band
                    header = _las_header({name: v.dtype for name, v in values.items()}, intensity_per_count,
                                         descriptions, metadata)
                    writer = open_writer.enter_context(laspy.open(stream, mode="w", header=header,
                                                                  do_compress=compress,
                                                                  laz_backend=backend if compress else None,
                                                                  closefd=False))
                marked = (np.zeros(xyz.shape[0], bool) if withheld is None
                          else np.asarray(withheld, bool).reshape(-1)[keep])
                writer.write_points(_las_records(writer.header, xyz, values, marked, intensity_per_count))
    return path


def _row_bands(height: int, width: int) -> list[slice]:
    """Bands of rows of about :data:`LAS_BAND_PIXELS` pixels (one band for an empty grid)."""
    step = max(1, LAS_BAND_PIXELS // max(width, 1))
    return [slice(start, min(height, start + step)) for start in range(0, height, step)] or [slice(0, 0)]


def _las_header(dtypes: Mapping[str, np.dtype], per_count: float, descriptions: Mapping[str, str] | None,
                metadata: Mapping[str, object] | None) -> Any:
    """The LAS header: point format 6, the fields of ``dtypes`` (the pixel indices included) as extra bytes, and
    the JSON record."""
    import laspy

    described = {**FIELD_DESCRIPTIONS, **(descriptions or {})}
    described = {name: described.get(name, name) for name in dtypes if name not in RETURN_FIELDS}
    record: dict[str, object] = {"generator": generator(), "fields": described}
    if INTENSITY_FIELD in dtypes:
        described[INTENSITY_FIELD] = f"{described[INTENSITY_FIELD]} = {per_count:.2e} * I"
        record["intensity"] = {"field": INTENSITY_FIELD, "per_count": per_count,
                               "meaning": f"{INTENSITY_FIELD} = intensity * per_count, the same scale in every file; "
                                          f"intensity {INTENSITY_MAX} (clipped) at and above "
                                          f"{INTENSITY_MAX * per_count:.4g}"}
    record["withheld"] = (f"withheld points (classification {LAS_CLASS_LOW_NOISE}, low point/noise) are invalid "
                          f"pixels; the others have classification {LAS_CLASS_UNCLASSIFIED}")
    record.update(metadata or {})
    header = laspy.LasHeader(version="1.4", point_format=6)
    header.generating_software = generator()[:32]
    header.system_identifier = "OTHER"
    header.scales = np.full(3, LAS_SCALE_M)
    header.offsets = np.zeros(3)
    header.add_extra_dims([laspy.ExtraBytesParams(name=name, type=dtype,
                                                  description=described[name][:LAS_DESCRIPTION_CHARS])
                           for name, dtype in dtypes.items() if name not in RETURN_FIELDS])
    header.vlrs.append(laspy.VLR(user_id=LAS_METADATA_USER_ID, record_id=LAS_METADATA_RECORD_ID,
                                 description="JSON metadata", record_data=json.dumps(record).encode()))
    return header


def _las_records(header: Any, xyz: NDArray, values: dict[str, NDArray], withheld: NDArray[np.bool_],
                 scale: float) -> Any:
    """The packed point records of one band, filled column by column (laspy's per-dimension setters copy and
    scale each one again)."""
    import laspy

    records = np.zeros(xyz.shape[0], dtype=header.point_format.dtype())
    for axis, name in enumerate("XYZ"):
        records[name] = np.rint((xyz[:, axis] - header.offsets[axis]) / LAS_SCALE_M)
    records["bit_fields"] = _RETURN_BITS
    if all(name in values for name in RETURN_FIELDS):
        numbers, counts = (np.asarray(values[name], dtype=np.uint8) & 0x0F for name in RETURN_FIELDS)
        records["bit_fields"] = numbers | (counts << 4)
    if INTENSITY_FIELD in values:
        records["intensity"] = intensity_counts(values[INTENSITY_FIELD], scale)
    records["classification_flags"] = np.where(withheld, _WITHHELD_BIT, 0)
    records["classification"] = np.where(withheld, LAS_CLASS_LOW_NOISE, LAS_CLASS_UNCLASSIFIED)
    for name, v in values.items():
        if name not in RETURN_FIELDS:
            records[name] = v
    return laspy.PackedPointRecord(records, header.point_format)


def las_metadata(path: str | Path) -> dict[str, object]:
    """The JSON record of a LAS/LAZ file written by :func:`write_las` (empty if it has none)."""
    import laspy

    with laspy.open(path) as reader:
        for vlr in reader.header.vlrs:
            if vlr.user_id == LAS_METADATA_USER_ID and vlr.record_id == LAS_METADATA_RECORD_ID:
                return json.loads(bytes(vlr.record_data).decode())
    return {}


def write_ply(path: str | Path, points: NDArray, fields: Mapping[str, NDArray], colors: NDArray | None = None,
              comments: tuple[str, ...] = (), second: PlyReturns | None = None) -> Path:
    """Write a binary little-endian PLY: float32 x, y, z [m], uchar red, green, blue when ``colors`` (H, W, 3)
    uint8 are given, and one property ``scalar_<name>`` per field; ``comments`` go to the header after the
    generator's. ``points`` (H, W, 3) [m], ``fields`` name -> (H, W) array; ``second``: some pixels' second
    returns (:data:`PlyReturns`), vertices after the first returns', coloured as their pixel; see the module
    docstring.
    """
    path = Path(path)
    xyz, values, keep = _points_and_fields(points, fields)
    if second is not None:
        more_xyz, more_values, more_keep = _points_and_fields(*second)
        if set(more_values) != set(values):
            raise ValueError(f"the second returns' fields {sorted(more_values)} must be the first's {sorted(values)}")
        xyz = np.concatenate([xyz, more_xyz])
        values = {name: np.concatenate([v, more_values[name].astype(v.dtype)]) for name, v in values.items()}
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
        if second is not None:
            kept_colours = np.concatenate([kept_colours, colors.reshape(-1, 3)[more_keep]])
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
