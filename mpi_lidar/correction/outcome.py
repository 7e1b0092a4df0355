"""What happened to one scan of a batch, and the status its pixel counts earn."""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field

from mpi_lidar.correction.options import INVALID_FLAGS, MODEL_FLAGS, Flag, ScanStatus, UnservedReason

# What each invalid flag says of a pixel, as a degraded scan's reason names it.
INVALID_CAUSES = {
    Flag.NOT_FINITE: "its depth or amplitude is not finite",
    Flag.NO_RETURN: "no return above the noise",
    Flag.SATURATED: "its amplitude is saturated",
    Flag.INCONSISTENT: "its frequencies' depths disagree beyond their noise",
    Flag.BEYOND_AMBIGUITY: "its range lies past the frequencies' combined ambiguity",
}


def invalid_share(counts: Mapping[str, int]) -> float:
    """Share of a scan's pixels flagged invalid (not finite, no return, saturated, inconsistent); 0 if none."""
    total = sum(counts.values())
    return sum(counts.get(flag.name.lower(), 0) for flag in INVALID_FLAGS) / total if total else 0.0


def first_cause(counts: Mapping[str, int]) -> Flag | None:
    """The invalid flag that holds most of a scan's invalid pixels (the earlier flag on a tie), None if none."""
    held = [(counts.get(flag.name.lower(), 0), -index, flag) for index, flag in enumerate(INVALID_FLAGS)]
    count, _, flag = max(held)
    return flag if count > 0 else None


def scan_status(counts: Mapping[str, int], max_invalid_share: float,
                unserved: UnservedReason | None = None) -> ScanStatus:
    """How a scan whose outputs were written ended, from its flag counts (:meth:`Correction.counts`) and the
    reason the model could not serve it, if any (:attr:`Correction.unserved`): the one place that decides it.

    The first cause wins. degraded: more than ``max_invalid_share`` of its pixels are invalid, for a cause the
    model has no part in (not finite, no return, inconsistent, beyond the ambiguity): the data are what is
    wrong, whatever else was found; unserved: the model cannot serve the scan (its amplitudes saturate almost
    everywhere or contradict their unit, as those of another unit do, or no pixel that may need correction
    could be corrected: out of the model's range, ambiguous range, no geometry for a geometric model);
    degraded, too, where the invalid pixels are mostly saturated and the model could serve the scan;
    unchanged: no pixel was corrected and none needed the model; corrected: some were (beyond the training prior
    or within it).
    """
    over = invalid_share(counts) > max_invalid_share
    if over and first_cause(counts) != Flag.SATURATED:
        return ScanStatus.DEGRADED
    if unserved is not None:
        return ScanStatus.UNSERVED
    if over:
        return ScanStatus.DEGRADED
    corrected = sum(counts.get(flag.name.lower(), 0) for flag in MODEL_FLAGS)
    return ScanStatus.CORRECTED if corrected > 0 else ScanStatus.UNCHANGED


def degraded_reason(counts: Mapping[str, int]) -> str:
    """Why a scan is degraded, its first cause first: ``82.0 % of its pixels are invalid, first no return (80.0
    %: no return above the noise)``, then the other invalid flags' shares."""
    total = max(sum(counts.values()), 1)
    cause = first_cause(counts)
    if cause is None:
        return "no pixel is invalid"
    others = [f"{flag.name.lower()} {100 * counts.get(flag.name.lower(), 0) / total:.1f} %" for flag in INVALID_FLAGS
              if flag != cause and counts.get(flag.name.lower(), 0)]
    return (f"{100 * invalid_share(counts):.1f} % of its pixels are invalid, first {cause.name.lower()} "
            f"({100 * counts.get(cause.name.lower(), 0) / total:.1f} %: {INVALID_CAUSES[cause]})"
            + (f"; then {', '.join(others)}" if others else ""))


def status_reason(status: ScanStatus, counts: Mapping[str, int], unserved: Unserved | None) -> str:
    """The reason a scan of this ``status`` states (:func:`scan_status`): a degraded scan's first cause, an
    unserved one's message, else nothing."""
    if status == ScanStatus.DEGRADED:
        return degraded_reason(counts)
    if status == ScanStatus.UNSERVED and unserved is not None:
        return unserved.message
    return ""


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
