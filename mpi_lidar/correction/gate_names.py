"""The gates' names, the one place they live: options, the command line, the flows and the benchmarks take them
from here (a module of its own, so that ``mpi-lidar --help`` imports nothing else for them)."""

from __future__ import annotations

from enum import StrEnum


class GateName(StrEnum):
    """The gates (:mod:`mpi_lidar.correction.gates`): which valid pixels the model corrects.

    geometry: where the scan's geometry lets multipath reach the threshold; all: every valid pixel;
    consistency: where the frequencies' depths disagree beyond their noise.
    """

    GEOMETRY = "geometry"
    ALL = "all"
    CONSISTENCY = "consistency"


GATES: tuple[str, ...] = tuple(gate.value for gate in GateName)
