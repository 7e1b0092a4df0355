"""The benchmark of the correction model beyond its prior's d_AS range (benchmarks/model_range.py)."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

from benchmarks.model_range import BELOW, bins_m, run
from mpi_lidar.learning.model import load_model
from tests.model_factory import tiny_model

ROOT = Path(__file__).resolve().parents[2]


@pytest.fixture(scope="module")
def model_dir(tmp_path_factory) -> Path:
    return tiny_model(tmp_path_factory.mktemp("range") / "model")


@pytest.mark.unit
def test_bins__span_both_ends_of_the_prior():
    spans = bins_m((1.4, 2.4))
    assert spans[0][0] == pytest.approx(0.98) and spans[-1][1] == pytest.approx(2.64)
    assert all(low < high for low, high in spans)


@pytest.mark.unit
def test_run__the_range_rule_corrects_inside_and_keeps_raw_outside(model_dir):
    found = list(run(load_model(model_dir), rows=1_500))
    below, above = found[:len(BELOW)], found[len(BELOW):]
    # true 0.98-1.12 m: measured below 1.19 m, so raw; 1.26-1.40 m: corrected; past 2.45 m: raw
    assert below[0].corrected_share == 0 and below[0].rule_mm == pytest.approx(below[0].raw_mm)
    for row in below[3:]:
        assert row.corrected_share == 1 and row.rule_mm == pytest.approx(row.model_mm)
    for row in above[2:]:
        assert row.corrected_share == 0 and row.rule_mm == pytest.approx(row.raw_mm)
    assert all(0 < row.weak_rows < row.rows and row.weak_raw_mm < row.raw_mm for row in found)


@pytest.mark.integration
@pytest.mark.slow
def test_command__prints_the_table(model_dir):
    result = subprocess.run([sys.executable, "-m", "benchmarks.model_range", "--model", str(model_dir),
                             "--rows", "500"], capture_output=True, text=True, timeout=300, cwd=ROOT)
    assert result.returncode == 0, result.stderr
    assert result.stdout.count("\n| ") == len(bins_m((1.4, 2.4))) + 1  # header and one row per bin
