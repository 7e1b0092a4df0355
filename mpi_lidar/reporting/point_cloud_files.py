"""Which point-cloud files a corrected scan's outputs hold, what they record, and their writing.

Every file's fields come from one function, :func:`point_cloud_fields` (the scan and its
:class:`~mpi_lidar.correction.Correction`: the measured, unwrapped range and the amplitude in V^2), which the Python
API offers as ``mpi_lidar.point_cloud_fields``. The corrected cloud as LAS/LAZ holds every valid pixel at its
corrected range, and a saturated or inconsistent pixel (flags 4-5) with a positive measured range at that range,
marked Withheld and classification 7 (noise); a pixel without a return or a finite depth, or past the combined
ambiguity distance (flags 2, 3 and 10), has no range it can be placed at and is left out, unless
``no_return_range_m`` places it on its ray at that range (Withheld too). Its JSON record carries the flag codes
(:mod:`mpi_lidar.reporting.legend`) and the frame (:func:`frame_record`). The PLY files (``raw.ply``,
``corrected.ply``) hold the valid pixels only, coloured by amplitude (corrected pixels in amber). Every file:
docs/reference/point-clouds.md."""

from __future__ import annotations

from collections.abc import Callable
from functools import partial
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from mpi_lidar.correction import MODEL_FLAGS, Correction, Flag
from mpi_lidar.correction.mixed import SecondReturns
from mpi_lidar.errors import MpiLidarError
from mpi_lidar.reporting.legend import FLAG_LEGEND, estimate_record, flag_record
from mpi_lidar.reporting.metrics import measured_depth
from mpi_lidar.reporting.output_levels import OutputLevel, check_outputs
from mpi_lidar.scans.geometry import point_cloud
from mpi_lidar.scans.pointcloud import (
    LAS_DESCRIPTION_CHARS,
    LasBand,
    PointCloudFormat,
    PointCloudFrame,
    correction_fields,
    in_frame,
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
FLAG_LETTERS = {flag: entry.letter for flag, entry in FLAG_LEGEND.items()}
# Invalid pixels without a range of their own: left out of the LAS/LAZ unless placed at a stated range.
RANGELESS_FLAGS = (Flag.NOT_FINITE, Flag.NO_RETURN, Flag.BEYOND_AMBIGUITY)
# How x, y, z follow from a pixel's azimuth and elevation (mpi_lidar.scans.scan.grid_rays).
SCANNER_FRAME = {
    "origin": "the scanner's optical centre",
    "units": "m",
    "x": "cos(elevation) * sin(azimuth) * range",
    "y": "sin(elevation) * range",
    "z": "cos(elevation) * cos(azimuth) * range",
    "handedness": "right-handed: +z is the ray at azimuth 0 and elevation 0, elevation turns towards +y, azimuth "
                  "turns from +z towards +x (counter-clockwise seen from +y); +x is the scanner's left",
    "row": "index of the scan's elevation_rad (or of its ray_directions' first axis)",
    "column": "index of the scan's azimuth_rad (or of its ray_directions' second axis)",
    "rays": "a scan stored with ray_directions uses those unit vectors as they are",
}
# How a pixel resolved into two returns (flag two_returns) lies in the files that hold its second return.
TWO_RETURNS_RECORD = ("a pixel resolved into two returns (flag 12) is two points at its two ranges, return 1 (the "
                      "nearer) and return 2 (the farther) of 2; corrected_range_m is each point's range and "
                      "return_share its share of the two returns' light; every other point is return 1 of 1, share 1")
CORRECTED_RGB = np.array([1.0, 0.62, 0.15])  # amber, times the amplitude's grey level
_PERCENTILE_SAMPLE = 100_000  # amplitudes the colour scale's 99th percentile is taken on


def flag_description() -> str:
    """The LAS ``flag`` description: each code with its letter of :data:`FLAG_LETTERS` ("0C 1N 2F ..."),
    without spaces if they do not fit 31 characters, and as the letters in code order ("flags 0-13: CNF...")
    if even that does not fit (the codes run 0, 1, 2, ... without a gap)."""
    spaced = " ".join(f"{int(flag)}{FLAG_LETTERS[flag]}" for flag in Flag)
    for text in (spaced, spaced.replace(" ", "")):
        if len(text) <= LAS_DESCRIPTION_CHARS:
            return text
    return f"flags 0-{len(Flag) - 1}: " + "".join(FLAG_LETTERS[flag] for flag in sorted(Flag))


def frame_record(frame: str = PointCloudFrame.SCANNER) -> dict[str, str]:
    """How a file's x, y, z follow from a pixel's azimuth, elevation and range in ``frame``
    (:class:`~mpi_lidar.scans.pointcloud.PointCloudFrame`)."""
    if PointCloudFrame(frame) == PointCloudFrame.SCANNER:
        return {"name": PointCloudFrame.SCANNER.value, **SCANNER_FRAME}
    return {"name": PointCloudFrame.Z_UP.value, "origin": SCANNER_FRAME["origin"], "units": "m",
            "x": "cos(elevation) * cos(azimuth) * range (forward)",
            "y": "cos(elevation) * sin(azimuth) * range (the scanner's left)",
            "z": "sin(elevation) * range (up)",
            "handedness": "right-handed, z up: the scanner frame's axes (z, x, y) as (x, y, z)",
            "row": SCANNER_FRAME["row"], "column": SCANNER_FRAME["column"], "rays": SCANNER_FRAME["rays"]}


def cloud_placement(frame: str = PointCloudFrame.SCANNER, no_return_range_m: float | None = None) -> str:
    """Where a scan's point clouds put their points, in one line: recorded with its outputs (the
    ``point_cloud_placement`` of its ``corrected.zarr``) and compared when a batch runs again into them."""
    frame = PointCloudFrame(frame).value
    if no_return_range_m is None:
        return f"frame {frame}; pixels without a range left out"
    return f"frame {frame}; pixels without a range withheld at {no_return_range_m:g} m"


def point_cloud_metadata(frame: str = PointCloudFrame.SCANNER, no_return_range_m: float | None = None,
                         two_returns: bool = False) -> dict[str, object]:
    """What the LAS/LAZ JSON record adds to the writer's own: the flag codes, the estimates and the frame, where
    withheld points lie and, where some pixel was resolved into two returns (``two_returns``), what its points are."""
    placed = ("left out" if no_return_range_m is None
              else f"withheld at {no_return_range_m:g} m on their ray (raw_range_m keeps what was measured)")
    returns = {"returns": TWO_RETURNS_RECORD} if two_returns else {}
    return {
        "flags": flag_record(),
        "estimates": estimate_record(),
        "frame": frame_record(frame),
        "withheld_points": {"saturated, inconsistent": "withheld at their measured range where it is positive, "
                                                       "else as not finite",
                            "not finite, no return, beyond ambiguity": placed},
        **returns,
    }


def point_cloud_fields(scan: Scan, correction: Correction, rows: slice = slice(None)) -> dict[str, NDArray]:
    """The per-point fields of a corrected scan's rows (each (h, W)), as every point cloud of it holds them: those of
    :func:`~mpi_lidar.scans.pointcloud.correction_fields` from the correction's measured range (unwrapped where the
    scan's depths wrapped: :attr:`Correction.measured_depth`) and the scan's highest-frequency amplitude in V^2
    (divided by :attr:`Correction.amplitude_units_per_v2`), with the uncertainty where the correction has one."""
    amplitude = np.asarray(scan.amplitude[-1, rows], dtype=np.float32) / np.float32(correction.amplitude_units_per_v2)
    uncertainty = correction.uncertainty_m
    return correction_fields(measured_depth(scan, correction, rows), correction.depth[rows], correction.flags[rows],
                             amplitude, None if uncertainty is None else uncertainty[rows])


def two_return_fields(second: SecondReturns, fields: dict[str, NDArray], rows: slice = slice(None)
                      ) -> tuple[dict[str, NDArray], NDArray[np.float32], dict[str, NDArray]]:
    """The point-cloud fields of a correction that resolved some pixel into two returns (``second``, the
    correction's :attr:`~mpi_lidar.correction.Correction.second_returns`): the pixels' ``fields`` (those of
    :func:`point_cloud_fields` for ``rows``) with each one's return number, number of returns (the nearer return
    is 1 of 2, a single one 1 of 1) and ``return_share`` of the light added; the second returns' ranges (h, W) [m]
    (NaN where a pixel has none); and their fields (the pixel's, at the second range, with the second return's
    own uncertainty where the correction has one).
    A correction without a resolved pixel has none of these: its files hold what they always did."""
    ranges = np.asarray(second.depth_m[rows], dtype=np.float32)
    share = np.asarray(second.share[rows], dtype=np.float32)
    resolved = np.isfinite(ranges)
    second_nearer = resolved & (ranges < fields["corrected_range_m"])
    count = np.where(resolved, 2, 1).astype(np.uint8)
    first = {**fields, "return_number": np.where(second_nearer, 2, 1).astype(np.uint8), "number_of_returns": count,
             "return_share": np.where(resolved, 1 - share, 1).astype(np.float32)}
    uncertainty = None
    if "uncertainty_m" in fields:
        uncertainty = (np.full(ranges.shape, np.nan, np.float32) if second.sigma_m is None
                       else np.asarray(second.sigma_m[rows], dtype=np.float32))
    other = {**correction_fields(fields["raw_range_m"], ranges, fields["flag"], fields["amplitude_v2"], uncertainty),
             "return_number": np.where(second_nearer, 1, 2).astype(np.uint8), "number_of_returns": count,
             "return_share": np.where(resolved, share, np.nan).astype(np.float32)}
    return first, ranges, other


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
    corrected = np.isin(np.asarray(flags), MODEL_FLAGS)
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


def write_point_clouds(directory: Path, formats: tuple[PointCloudFormat, ...], rays: NDArray | RayRows, scan: Scan,
                       correction: Correction, *, frame: str = PointCloudFrame.SCANNER,
                       no_return_range_m: float | None = None) -> list[str]:
    """The point clouds of ``formats`` of a corrected scan into ``directory``; returns the names of the files written.

    ``rays`` (H, W, 3) unit rays, or a :class:`~mpi_lidar.scans.scan.RayRows` where no PLY is written (the LAS
    and LAZ files are built a band of rows at a time, the PLY files whole). Each file's fields are those of
    :func:`point_cloud_fields`; its coordinates in ``frame`` (``scanner`` or ``z-up``). ``no_return_range_m``: the
    range [m] at which the LAS/LAZ places pixels without a range (not finite, no return), withheld; None leaves them
    out.
    """
    if not formats:
        return []
    if no_return_range_m is not None and not (np.isfinite(no_return_range_m) and no_return_range_m > 0):
        raise MpiLidarError(f"no_return_range_m must be a positive number of metres, got {no_return_range_m!r}")
    written = []
    if PointCloudFormat.PLY in formats:
        written += _write_ply_files(directory, rays[:], scan, correction, frame)  # a RayRows builds every row
    las_formats = [fmt for fmt in (PointCloudFormat.LAS, PointCloudFormat.LAZ) if fmt in formats]
    if las_formats:
        band, second = _las_bands(rays, scan, correction, frame, no_return_range_m)
        for fmt in las_formats:
            (name,) = POINT_CLOUD_FILES[fmt]
            write_las_bands(directory / name, np.shape(correction.flags), band, compress=fmt == PointCloudFormat.LAZ,
                            descriptions={"flag": flag_description()},
                            metadata=point_cloud_metadata(frame, no_return_range_m, second is not None),
                            second=second)
            written.append(name)
    return [name for fmt in formats for name in POINT_CLOUD_FILES[fmt] if name in written]


def las_ranges(fields: dict[str, NDArray], no_return_range_m: float | None = None
               ) -> tuple[NDArray[np.float32], NDArray[np.bool_]]:
    """Where each pixel's LAS/LAZ point lies along its ray [m] (NaN: no point) and which points are withheld: a valid
    pixel at its corrected range; an invalid one withheld, at its measured range where that is positive and the
    pixel has a return, else at ``no_return_range_m`` (None: no point). Never behind the scanner."""
    corrected, raw = fields["corrected_range_m"], fields["raw_range_m"]
    valid = np.isfinite(corrected)
    rangeless = np.isin(fields["flag"], [int(f) for f in RANGELESS_FLAGS]) | ~(raw > 0)
    stated = np.float32(np.nan if no_return_range_m is None else no_return_range_m)
    ranges = np.where(valid, corrected, np.where(rangeless, stated, raw)).astype(np.float32)
    return ranges, ~valid & np.isfinite(ranges)


def _write_ply_files(directory: Path, rays: NDArray, scan: Scan, correction: Correction, frame: str) -> list[str]:
    """``raw.ply`` (the valid pixels at their raw range) and ``corrected.ply`` (at their corrected range, with the
    second returns of the pixels resolved into two, as :func:`two_return_fields` gives them); their names."""
    fields = point_cloud_fields(scan, correction)
    valid = np.isfinite(fields["corrected_range_m"])
    colors = point_cloud_colors(fields["flag"], fields["amplitude_v2"])
    comments = (f"scalar_flag codes: {flag_description()} (docs/reference/point-clouds.md)",
                f"frame: {frame_record(frame)['handedness']}")
    raw_name, corrected_name = POINT_CLOUD_FILES[PointCloudFormat.PLY]
    write_ply(directory / raw_name, in_frame(point_cloud(np.where(valid, fields["raw_range_m"], np.nan), rays),
                                             frame), fields, colors, comments)
    second = None
    if correction.second_returns is not None:
        fields, ranges, other = two_return_fields(correction.second_returns, fields)
        second = (in_frame(point_cloud(ranges, rays), frame), other)
    write_ply(directory / corrected_name, in_frame(point_cloud(fields["corrected_range_m"], rays), frame), fields,
              colors, comments, second)
    return [raw_name, corrected_name]


def _las_bands(rays: NDArray | RayRows, scan: Scan, correction: Correction, frame: str,
               no_return_range_m: float | None) -> tuple[Callable[[slice], LasBand], Callable[[slice], LasBand] | None]:
    """The LAS/LAZ file's points a band of rows at a time, placed as :func:`las_ranges` says, and the second
    returns' (None where no pixel was resolved into two: :func:`two_return_fields`)."""
    resolved = correction.second_returns

    def band(rows: slice) -> LasBand:
        fields = point_cloud_fields(scan, correction, rows)
        ranges, withheld = las_ranges(fields, no_return_range_m)
        if resolved is not None:
            fields = two_return_fields(resolved, fields, rows)[0]
        return in_frame(point_cloud(ranges, rays[rows]), frame), fields, withheld

    def second(rows: slice, resolved: SecondReturns) -> LasBand:
        _, ranges, other = two_return_fields(resolved, point_cloud_fields(scan, correction, rows), rows)
        return in_frame(point_cloud(ranges, rays[rows]), frame), other, None

    return band, None if resolved is None else partial(second, resolved=resolved)
