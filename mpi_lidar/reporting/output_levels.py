"""How much a corrected scan's outputs hold: the output levels, from most to least."""

from __future__ import annotations

from dataclasses import dataclass
from enum import StrEnum

from mpi_lidar.errors import MpiLidarError


class OutputLevel(StrEnum):
    """What a scan's outputs hold; each level holds what the next one holds.

    full: the store, metrics, report, maps, error histogram, point-cloud views, the point clouds (PLY and LAZ)
    and the 3-D view. light: the store, metrics, report, a thumbnail and the LAZ point cloud. data: the store and
    metrics only. Any level writes the point-cloud formats asked for instead (``--point-cloud``).
    """

    FULL = "full"
    LIGHT = "light"
    DATA = "data"


OUTPUT_LEVELS = tuple(level.value for level in OutputLevel)  # from most to least
# The default of a batch (``mpi-lidar correct``, the correction flow): the store, the report, a thumbnail and
# the LAZ point cloud cost little beside the correction itself (the LAZ 15-20 % of a megapixel scan's,
# docs/results/point-clouds.md); ``full`` (maps, histogram, point clouds as PLY and LAZ, 3-D view) costs as much
# as the correction again on a megapixel scan (docs/results/correction.md). ``--point-cloud`` picks the formats
# at any level. The pipeline's three demo scenes are written ``full``.
DEFAULT_OUTPUTS = OutputLevel.LIGHT.value


def check_outputs(outputs: str) -> OutputLevel:
    """``outputs`` as an output level; one clear error if it names none."""
    if outputs not in OUTPUT_LEVELS:
        raise MpiLidarError(f"unknown output level {outputs!r}; choose one of {', '.join(OUTPUT_LEVELS)}")
    return OutputLevel(outputs)


def covers(written: str | None, wanted: str) -> bool:
    """Whether outputs written at level ``written`` hold everything of level ``wanted`` (None: written
    before output levels existed, that is everything)."""
    written = written if written in OUTPUT_LEVELS else OutputLevel.FULL
    return OUTPUT_LEVELS.index(written) <= OUTPUT_LEVELS.index(check_outputs(wanted))


@dataclass(frozen=True)
class OutputFile:
    """A file of a scan's outputs: its ``name``, the lowest ``level`` that writes it (every level above writes it
    too), and what it ``holds``, with when it is left out, as the docs list it."""

    name: str
    level: OutputLevel
    holds: str


# Every file of a scan's outputs, from the lowest level up: the one list the docs' file lists are made from
# (docs/output_files.py). The point clouds are those of the level's default formats (--point-cloud picks others).
OUTPUT_FILES = (
    OutputFile("corrected.zarr", OutputLevel.DATA, "the corrected depth, per-pixel flags, the expected multipath "
               "bias, and the scan, model and options hashes; see [stores](reference/stores.md)"),
    OutputFile("metrics.json", OutputLevel.DATA, "counts, metrics, notes and the files written"),
    OutputFile("report.md", OutputLevel.LIGHT, "the report"),
    OutputFile("report.html", OutputLevel.LIGHT, "the report; at `full` with an interactive 3-D view: one "
               "`plotly.min.js` shared by the batch, in the output folder, no network needed"),
    OutputFile("thumbnail.png", OutputLevel.LIGHT, "corrected depth and flags, at most 512 pixels wide, over a "
               "colour key"),
    OutputFile("corrected.laz", OutputLevel.LIGHT, "the point cloud, with scan geometry; see [point clouds]"
               "(reference/point-clouds.md)"),
    OutputFile("maps.png", OutputLevel.FULL, "raw and corrected depth, amplitude, the applied correction, the "
               "expected multipath bias, error maps where there is a reference, flags; axes in degrees"),
    OutputFile("error_hist.png", OutputLevel.FULL, "the depth errors before and after correction; with a "
               "reference depth"),
    OutputFile("point_cloud.png", OutputLevel.FULL, "top views of the raw and corrected point clouds, and a side "
               "profile of one column with how far correction moved its points; with scan geometry"),
    OutputFile("raw.ply", OutputLevel.FULL, "the measured point cloud; with scan geometry"),
    OutputFile("corrected.ply", OutputLevel.FULL, "the corrected point cloud; with scan geometry"),
)


def level_files(outputs: str) -> tuple[OutputFile, ...]:
    """The files of the outputs at level ``outputs``: its own and those of every level below it
    (:data:`OUTPUT_FILES`), in their order."""
    return tuple(file for file in OUTPUT_FILES if covers(outputs, file.level))
