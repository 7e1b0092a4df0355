"""The point-cloud benchmark runs at tiny sizes and prints its table (rows and columns checked, not timings)."""

from __future__ import annotations

import pytest

from benchmarks import point_clouds as bench

pytestmark = pytest.mark.integration


def test_benchmark_point_clouds__quick_prints_the_table(tmp_path):
    text = bench.run(bench.Plan.quick(), None, tmp_path)
    assert text.startswith("Machine: ") and "load average" in text
    lines = [line for line in text.splitlines() if line.startswith("| ")]
    assert tuple(cell.strip() for cell in lines[0].strip("|").split("|")) == bench.HEADERS
    runs = [line.split("|")[1].strip() for line in lines[1:]]
    assert runs[0].startswith("process_scan") and runs[1] == "correct_scan alone"
    assert [run.split(" (")[0] for run in runs[2:5]] == [f"write_point_clouds {fmt}" for fmt in ("laz", "las", "ply")]
    assert "corrected.laz" in runs[2] and "raw.ply, corrected.ply" in runs[4] and runs[5].startswith("LAZ as written")
    laz = [cell.strip() for cell in lines[3].strip("|").split("|")]
    assert laz[7] == "<= 20 %" and laz[8] in ("yes", "no") and float(laz[4]) > 0 and laz[6].endswith(" %")
    assert all(line.count("|") == lines[0].count("|") for line in lines)
