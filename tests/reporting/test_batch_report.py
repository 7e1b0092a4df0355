"""The batch report: one table over the scans of a batch (more in tests/workflows/test_correct_archive.py)."""

from __future__ import annotations

from mpi_lidar.correction import ScanOutcome, ScanStatus
from mpi_lidar.reporting.batch_report import GATED_OUT, batch_report


def test_batch_report__gated_out_counts_both_skip_flags():
    outcome = ScanOutcome("s.scan.zarr", "s", "corrected",
                          counts={"corrected": 4, "not_needed": 1, "no_multipath": 3, "not_finite": 2})
    report = batch_report([outcome], 1.0).markdown()
    assert "gated out" in report and "| 40.0 % |" in report


def test_batch_report__counts_every_status_and_escapes_cells():
    assert GATED_OUT == ("not_needed", "no_multipath", "uncalibrated")
    outcomes = [ScanOutcome("a.scan.zarr", "a", ScanStatus.FAILED, reason="bad | chunk"),
                ScanOutcome("b.scan.zarr", "b", ScanStatus.SKIPPED, reason="already corrected",
                            kept_status=ScanStatus.DEGRADED)]
    report = batch_report(outcomes, 2.0).markdown()
    assert "2 scans in 2.0 s: 0 corrected, 0 unchanged, 0 degraded, 0 unserved, 1 already done, 1 failed." in report
    assert "bad \\| chunk" in report and "already corrected (degraded)" in report
