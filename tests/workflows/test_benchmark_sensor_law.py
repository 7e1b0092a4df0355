"""The sensor-law benchmark at small sizes: its tables, and the targets it measures on its quick scans."""

from __future__ import annotations

import re

import pytest

from benchmarks.sensor_law import main

pytestmark = pytest.mark.integration


def _tables(out: str) -> list[list[dict[str, str]]]:
    """Each markdown table printed, as rows of cells by header."""
    tables, header = [], None
    for line in out.splitlines():
        if not line.startswith("|"):
            header = None
            continue
        cells = [cell.strip() for cell in line.strip().strip("|").split("|")]
        if header is None:
            header = cells
            tables.append([])
        elif not line.startswith("|---"):
            tables[-1].append(dict(zip(header, cells, strict=True)))
    return tables


def test_sensor_law_benchmark__quick_fuses_near_ideal_keeps_units_apart_and_flags_the_far_wall(capsys):
    main(["--quick"])
    out = capsys.readouterr().out
    scans, tens, special = _tables(out)
    assert len(scans) == 6, out
    for row in scans:
        assert abs(float(row["fused / ideal MAE"]) - 1.0) < 0.05, f"fused within 5 % of ideal: {row}"
        assert 0.6 <= float(row["1-sigma coverage"].rstrip("%")) / 100 <= 0.76, f"coverage: {row}"
        assert float(row["uncalibrated"].rstrip("%")) < 1.0, row
        for unit in ("x 4000 max diff [mm]", "x 0.01 max diff [mm]"):
            difference, status, lost = re.fullmatch(r"([\d.]+) \((\w+), (\d+) lost\)", row[unit]).groups()
            assert float(difference) <= 0.05 and lost == "0", f"{unit}: {row}"
            assert status == "unserved" or float(difference) == 0.0, f"never corrected differently: {row}"
    for row in tens:
        assert row["status"] != "degraded", row
        ours, theirs = (float(row[key].rstrip("%")) for key in ("mis-unwrapped (ours)", "exhaustive ML, same pixels"))
        assert ours <= 2 * theirs + 0.1, f"within twice the exhaustive unwrapper's rate: {row}"
    (far,) = special
    assert float(far["bright wall at 26 m: valid near 2 m"].rstrip("%")) == 0.0
    assert float(far["flagged beyond ambiguity"].rstrip("%")) > 99.0
    assert float(far["3 % ramp 0.5-4 m flagged"].rstrip("%")) <= 1.0
