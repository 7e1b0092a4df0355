"""The per-corner-strength benchmark at tiny sizes: a row per scene, and the partners' light summed against the
dominant partner's."""

from __future__ import annotations

import subprocess
import sys

import pytest

from benchmarks.corner_strength import HEADER, cases
from tests.model_factory import tiny_model


def _table(stdout: str, header: str) -> list[list[str]]:
    lines = stdout.splitlines()
    table = lines[lines.index(header) + 2:]
    rows = table[:table.index("")] if "" in table else table
    return [[cell.strip() for cell in line.strip("|").split("|")] for line in rows]


@pytest.mark.integration
def test_corner_strength__a_row_per_scene_with_its_footprint_and_shares(tmp_path):
    model = tiny_model(tmp_path / "model")
    done = subprocess.run([sys.executable, "-m", "benchmarks.corner_strength", "--model", str(model), "--shrink",
                           "8"], capture_output=True, text=True, check=True, timeout=300)
    rows = _table(done.stdout, HEADER.splitlines()[0])
    assert [cells[0] for cells in rows] == [case.label for case in cases()]
    for cells in rows:
        assert cells[1].count("->") == 1 and cells[1].split("->")[1].count("/") == 2, cells
        assert 0.0 <= float(cells[6].rstrip(" %")) <= 100.0
        assert int(cells[7].split()[0]) >= 0
    assert all(cells[3] == "" for cells in rows if cells[0].startswith("corner")), "a corner has no tri-corner"


@pytest.mark.slow
@pytest.mark.integration
def test_corner_strength__partners_summed_predict_the_bias_better_than_the_dominant_one():
    done = subprocess.run([sys.executable, "-m", "benchmarks.corner_strength", "--partners", "--shrink", "8"],
                          capture_output=True, text=True, check=True, timeout=300)
    rows = _table(done.stdout, done.stdout.splitlines()[0])
    assert len(rows) == 6
    for cells in rows[1:3] + rows[4:]:  # at 0.024 and 0.073 m^2: enough pixels with multipath
        summed, dominant = (float(cells[k].split()[0]) for k in (4, 5))
        assert summed < dominant, cells


@pytest.mark.integration
def test_corner_strength__path_traced_by_mitsuba_gives_the_same_rows(tmp_path):
    model = tiny_model(tmp_path / "model")
    done = subprocess.run([sys.executable, "-m", "benchmarks.corner_strength", "--model", str(model), "--shrink",
                           "8", "--renderer", "mitsuba", "--samples", "256"], capture_output=True, text=True,
                          check=True, timeout=300)
    assert "Mitsuba 3 path traced, 256 paths per pixel" in done.stdout
    rows = _table(done.stdout, HEADER.splitlines()[0])
    assert [cells[0] for cells in rows] == [case.label for case in cases()]
    for cells in rows:
        raw, noise_floor = float(cells[1].split("->")[0]), float(cells[1].split("/")[-1])
        assert raw > 0 and noise_floor > 0, cells
    strong = [float(cells[1].split("->")[0]) for cells in rows if cells[0].startswith("corner 60")]
    assert strong[0] > 3 * float(rows[0][1].split("->")[0]), "the strong corner's multipath is in the raw depth"
