"""The batch report: one table over the scans of a batch (more in tests/workflows/test_correct_archive.py)."""

from __future__ import annotations

import pytest

from mpi_lidar.correction import ScanOutcome, ScanStatus
from mpi_lidar.reporting.batch_report import GATED_OUT, batch_report
from mpi_lidar.reporting.report import Table

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
    assert "- n1: bad | chunk" in report and "already corrected (degraded)" in report


def test_batch_report__report_link_second_and_no_valid_pixel_in_words(tmp_path):
    scan_dir = tmp_path / "dark"
    scan_dir.mkdir()
    (scan_dir / "report.html").write_text("<html></html>")
    outcome = ScanOutcome("dark.scan.zarr", "dark", ScanStatus.DEGRADED, output=str(scan_dir),
                          counts={"corrected": 0, "no_return": 6},
                          metrics={"whole map": {"pixels": 0, "raw_mae_m": float("nan"),
                                                 "corrected_mae_m": float("nan")}})
    report = batch_report([outcome], 1.0, tmp_path / "summary")
    table = next(b for b in report.blocks if isinstance(b, Table))
    assert table.headers == ("scan", "report", "status", "gated out", "invalid", "seconds", "notes"), "no empty MAE"
    row = table.rows[0]
    assert row[:3] == ("dark", "[report](../dark/report.html)", "⚠ degraded")
    assert "nan" not in " ".join(row) and row[-1] == "n1"
    assert "no valid pixel" in report.html() and "<details>" in report.html()


def test_batch_report__problems_first_marked_short_cells_notes_collapsed():
    long_note = "the footprint estimate is not significant; " * 8
    outcomes = [ScanOutcome("a.scan.zarr", "a", ScanStatus.CORRECTED, counts={"corrected": 5}, notes=(long_note,)),
                ScanOutcome("b.scan.zarr", "b", ScanStatus.UNSERVED, reason="amplitude_units: " + long_note),
                ScanOutcome("c.scan.zarr", "c", ScanStatus.UNCHANGED, notes=(long_note,)),
                ScanOutcome("d.scan.zarr", "d", ScanStatus.FAILED, reason="damaged chunk")]
    report = batch_report(outcomes, 1.0)
    table = next(b for b in report.blocks if isinstance(b, Table))
    assert [row[0] for row in table.rows] == ["d", "b", "a", "c"]
    assert [row[1] for row in table.rows] == ["⚠ failed", "⚠ unserved", "corrected", "unchanged"]
    assert all(len(cell) <= 40 for row in table.rows for cell in row)
    html = report.html()
    assert html.count("the footprint estimate is not significant") == 16, "each note once, in the details"
    assert "<details>" in html and "status-chart" in html and "1 unserved" in html
