"""The sensor-law benchmark at small sizes: its tables, and the targets it measures on its quick scans."""

from __future__ import annotations

import re

import pytest

from benchmarks.sensor_law import main

pytestmark = pytest.mark.integration


def test_sensor_law_benchmark__quick_fuses_near_ideal_and_flags_the_far_wall(capsys):
    main(["--quick"])
    out = capsys.readouterr().out
    rows = [line for line in out.splitlines() if line.startswith("| wall") or line.startswith("| ramp")]
    assert len(rows) == 6, out
    for line in rows:
        cells = [cell.strip() for cell in line.strip("|").split("|")]
        assert abs(float(cells[3]) - 1.0) < 0.05, f"fused within 5 % of ideal: {line}"
        assert 0.6 <= float(cells[4].rstrip("%")) / 100 <= 0.76, f"coverage: {line}"
    far = re.search(r"^\| ([\d.]+)% \| ([\d.]+)% \| ([\d.]+)% \|$", out, re.M)
    assert far is not None and float(far.group(1)) == 0.0 and float(far.group(2)) > 99.0 and float(far.group(3)) <= 1.0
