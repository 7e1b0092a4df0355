"""What happened to one scan of a batch, and the status its pixel counts earn."""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field

from mpi_lidar.correction.options import INVALID_FLAGS, ScanStatus, UnservedReason


def invalid_share(counts: Mapping[str, int]) -> float:
    """Share of a scan's pixels flagged invalid (not finite, no return, saturated, inconsistent); 0 if none."""
    total = sum(counts.values())
    return sum(counts.get(flag.name.lower(), 0) for flag in INVALID_FLAGS) / total if total else 0.0


def scan_status(counts: Mapping[str, int], max_invalid_share: float,
                unserved: UnservedReason | None = None) -> ScanStatus:
    """How a scan whose outputs were written ended, from its flag counts (:meth:`Correction.counts`) and the
    reason the model could not serve it, if any (:attr:`Correction.unserved`).

    unserved: the model cannot serve the scan (its amplitudes saturate almost everywhere, as those of another
    unit do, or no pixel that may need correction could be corrected: out of the model's range, ambiguous
    range, no geometry for a geometric model), checked first; degraded: more than ``max_invalid_share`` of
    its pixels are invalid; unchanged: no pixel was corrected and none needed the model; corrected: some were.
    """
    if unserved is not None:
        return ScanStatus.UNSERVED
    if invalid_share(counts) > max_invalid_share:
        return ScanStatus.DEGRADED
    return ScanStatus.CORRECTED if counts.get("corrected", 0) > 0 else ScanStatus.UNCHANGED


@dataclass(frozen=True)
class Unserved:
    """Why a model cannot serve a scan: a reason code and one line that names the command that helps."""

    reason: UnservedReason
    message: str

    def to_dict(self) -> dict[str, str]:
        return {"reason": str(self.reason), "message": self.message}


@dataclass(frozen=True)
class ScanOutcome:
    """What happened to one scan of a batch.

    ``source`` is the scan store's path, ``name`` the scan's own name, ``output`` its output directory.
    ``kept_status`` is, for a skipped scan, the status its existing outputs earn (corrected, unchanged or
    degraded, from their stored counts); None otherwise. ``reason`` says why a scan failed or was skipped.
    """

    source: str
    name: str
    status: ScanStatus
    reason: str = ""
    output: str = ""
    counts: dict[str, int] = field(default_factory=dict)
    metrics: dict[str, dict[str, float]] = field(default_factory=dict)
    seconds: float = 0.0
    notes: tuple[str, ...] = ()
    kept_status: ScanStatus | None = None
    unserved: UnservedReason | None = None

    @property
    def effective_status(self) -> ScanStatus:
        """What the scan's outputs are: a skipped scan's kept status, else its status (what ``--fail-on`` checks)."""
        return self.kept_status or self.status
