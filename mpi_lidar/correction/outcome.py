"""What happened to one scan of a batch."""

from __future__ import annotations

from dataclasses import dataclass, field

from mpi_lidar.correction.options import ScanStatus


@dataclass(frozen=True)
class ScanOutcome:
    """What happened to one scan of a batch."""

    source: str
    name: str
    status: ScanStatus
    reason: str = ""
    output: str = ""
    counts: dict[str, int] = field(default_factory=dict)
    metrics: dict[str, dict[str, float]] = field(default_factory=dict)
    seconds: float = 0.0
    notes: tuple[str, ...] = ()
