"""The batch report: one table over the scans of a batch (more in tests/workflows/test_correct_archive.py)."""

from __future__ import annotations

import pytest

from mpi_lidar.correction import ScanOutcome, ScanStatus
from mpi_lidar.reporting.batch_report import GATED_OUT, batch_report

pytestmark = pytest.mark.unit


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


def test_batch_report__report_link_second_and_no_valid_pixel_in_words(tmp_path):
    scan_dir = tmp_path / "dark"
    scan_dir.mkdir()
    (scan_dir / "report.html").write_text("<html></html>")
    outcome = ScanOutcome("dark.scan.zarr", "dark", ScanStatus.DEGRADED, output=str(scan_dir),
                          counts={"corrected": 0, "no_return": 6},
                          metrics={"whole map": {"pixels": 0, "raw_mae_m": float("nan"),
                                                 "corrected_mae_m": float("nan")}})
    table = batch_report([outcome], 1.0, tmp_path / "summary").blocks[1]
    assert table.headers[:3] == ("scan", "report", "status")
    row = table.rows[0]
    assert row[:3] == ("dark", "[report](../dark/report.html)", "degraded")
    assert row[5:9] == ("", "", "", "") and "no valid pixel" in row[10]
    assert "nan" not in " ".join(row)
