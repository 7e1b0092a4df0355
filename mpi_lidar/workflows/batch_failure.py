"""Which outcomes fail a batch, and the one line that says why."""

from __future__ import annotations

from collections.abc import Sequence

from mpi_lidar.correction import ScanOutcome, ScanStatus
from mpi_lidar.correction.options import FAIL_ON
from mpi_lidar.correction.outcome import degraded_reason
from mpi_lidar.errors import MpiLidarError


def failing_outcomes(outcomes: list[ScanOutcome], fail_on: Sequence[str] = (),
                     allow_unserved: bool = False) -> list[ScanOutcome]:
    """The outcomes that fail the batch: every failed scan, every unserved one unless ``allow_unserved``, and
    those whose status is in ``fail_on``.

    A skipped scan counts with the status its existing outputs earned (:attr:`ScanOutcome.effective_status`),
    so a re-run fails on a degraded scan as the first run did. Other names than :data:`FAIL_ON` are refused.
    """
    unknown = sorted(set(fail_on) - set(FAIL_ON))
    if unknown:
        raise MpiLidarError(f"fail_on takes {', '.join(FAIL_ON)}; not {', '.join(map(repr, unknown))}")
    statuses = {ScanStatus.FAILED, *(ScanStatus(status) for status in fail_on)}
    if not allow_unserved:
        statuses.add(ScanStatus.UNSERVED)
    return [o for o in outcomes if o.effective_status in statuses]


def failure_line(outcome: ScanOutcome) -> str:
    """``scan <source>: <why>``, one line, for an outcome that fails the batch."""
    return f"scan {outcome.source}: {_why(outcome)}"


def _why(outcome: ScanOutcome) -> str:
    if outcome.status == ScanStatus.FAILED:
        why = outcome.reason
    elif outcome.effective_status == ScanStatus.DEGRADED:
        why = f"degraded: {degraded_reason(outcome.counts)}"
    elif outcome.effective_status == ScanStatus.UNSERVED:
        why = f"unserved ({outcome.unserved}): {outcome.reason}" if outcome.status != ScanStatus.SKIPPED else (
            f"unserved ({outcome.unserved})")
    else:
        why = f"{outcome.effective_status}: no pixel was corrected"
    if outcome.status == ScanStatus.SKIPPED:
        why += " (existing outputs, already corrected with this model and options)"
    return why


def batch_failure(outcomes: list[ScanOutcome], fail_on: Sequence[str] = (),
                  allow_unserved: bool = False) -> str | None:
    """One line saying why the batch fails (``2 of 5 scans failed or degraded (...)``), or None if it does not."""
    bad = failing_outcomes(outcomes, fail_on, allow_unserved)
    if not bad:
        return None
    statuses = " or ".join(dict.fromkeys(str(o.effective_status) for o in bad))
    return f"{len(bad)} of {len(outcomes)} scans {statuses} ({'; '.join(f'{o.source}: {_why(o)}' for o in bad)})"
