"""How much a corrected scan's outputs hold: the output levels, from most to least."""

from __future__ import annotations

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
