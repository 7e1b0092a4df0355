"""The per-corner-strength benchmark at tiny sizes: a row per scene, and the partners' light summed against the
dominant partner's."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from benchmarks import light_budget
from benchmarks.corner_strength import HEADER, cases, exact_inputs
from mpi_lidar.config import Config
from tests.model_factory import tiny_model


def _table(stdout: str, header: str) -> list[list[str]]:
    lines = stdout.splitlines()
    table = lines[lines.index(header) + 2:]
    rows = table[:table.index("")] if "" in table else table
    return [[cell.strip() for cell in line.strip("|").split("|")] for line in rows]


@pytest.fixture(scope="module")
def model(tmp_path_factory) -> Path:
    """One tiny model for the module's runs that correct (they only read it)."""
    return tiny_model(tmp_path_factory.mktemp("corner_strength") / "model")


@pytest.mark.integration
def test_corner_strength__a_row_per_scene_with_its_footprint_and_shares(model):
    done = subprocess.run([sys.executable, "-m", "benchmarks.corner_strength", "--model", str(model), "--shrink",
                           "8"], capture_output=True, text=True, check=True, timeout=300)
    rows = _table(done.stdout, HEADER.splitlines()[0])
    assert [cells[0] for cells in rows] == [case.label for case in cases()]
    for cells in rows:
        assert cells[1].count("->") == 1 and cells[1].split("->")[1].count("/") == 3, cells
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
def test_corner_strength__path_traced_by_mitsuba_gives_the_same_rows(model):
    # 6 x 8 pixels a corner (every pixel path traced twice): the 60-degree corner's raw error stays about three
    # times the 90-degree one's, as at 12 x 16.
    done = subprocess.run([sys.executable, "-m", "benchmarks.corner_strength", "--model", str(model), "--shrink",
                           "16", "--renderer", "mitsuba", "--samples", "256", "--only", "corner"],
                          capture_output=True, text=True, check=True, timeout=300)
    assert "Mitsuba 3 path traced, 256 paths per pixel" in done.stdout
    rows = _table(done.stdout, HEADER.splitlines()[0])
    assert [cells[0] for cells in rows] == [case.label for case in cases() if "corner" in case.label]
    for cells in rows:
        raw, noise_floor = float(cells[1].split("->")[0]), float(cells[1].split("/")[-1])
        assert raw > 0 and noise_floor > 0, cells
    corner_60, corner_90 = (float(cells[1].split("->")[0]) for cells in rows[-2:])
    assert corner_60 > 1.5 * corner_90, "the 60-degree corner's stronger multipath is in the raw depth"


@pytest.mark.integration
def test_light_budget__the_stages_light_on_a_corner_is_its_renders_within_a_few_tens_of_percent():
    # 24 x 32 pixels a corner: the partner planes' single bounces against the renderer's, which shares their kernel.
    done = subprocess.run([sys.executable, "-m", "benchmarks.light_budget", "--shrink", "4", "--only", "corner"],
                          capture_output=True, text=True, check=True, timeout=300)
    rows = _table(done.stdout, light_budget.HEADER.splitlines()[0])
    assert [cells[0] for cells in rows] == [case.label for case in cases() if "corner" in case.label]
    for cells in rows:
        near, away = (int(count) for count in cells[1].split(" / "))
        assert near > 50 and away > 50, cells
        assert all(0.7 <= float(ratio) <= 1.4 for ratio in cells[2].split(" / ")), cells
        assert cells[4] == "-" and cells[6] == "0%", "two boards exchange no light among partners"


@pytest.mark.integration
def test_light_budget__path_traced_gives_all_the_light_only():
    # 24 x 32 pixels a corner at 256 paths: Mitsuba's light is not split into bounces, so only its sum is
    # compared; the partner planes' light is the independent tracer's within a factor of two (0.85-1.2 measured).
    done = subprocess.run([sys.executable, "-m", "benchmarks.light_budget", "--shrink", "4", "--only", "corner",
                           "--renderer", "mitsuba", "--samples", "256"],
                          capture_output=True, text=True, check=True, timeout=300)
    assert done.stdout.startswith("Mitsuba 3 path traced, 256 paths per pixel")
    rows = _table(done.stdout, light_budget.HEADER.splitlines()[0])
    assert [cells[0] for cells in rows] == [case.label for case in cases() if "corner" in case.label]
    for cells in rows:
        assert cells[3] == cells[4] == cells[6] == "-", cells
        assert all(0.5 <= float(ratio) <= 2.0 for ratio in cells[2].split(" / ")), cells


@pytest.mark.unit
def test_exact_inputs__recover_the_two_path_rho_aba_and_d_ab_a_render_was_made_of():
    config = Config()
    frequencies = np.asarray(config.frequencies_hz)
    c = config.sensor.speed_of_light_m_per_s
    ranges, albedo_cos = np.array([1.5, 2.0, 3.0]), np.array([0.7, 0.4, 0.2])
    rho_aba, d_ab = np.array([0.3, 1.2, 0.05]), np.array([0.1, 0.35, 0.02])
    direct = (config.sensor.gamma_r_v2 * albedo_cos / ranges**2)[:, None] * np.exp(
        4j * np.pi * np.outer(ranges, frequencies) / c)
    ratio = (rho_aba * albedo_cos)[:, None] * np.exp(4j * np.pi * np.outer(d_ab, frequencies) / c)
    found = exact_inputs(direct * (1 + ratio), direct, ranges, config)
    np.testing.assert_allclose(found, np.column_stack([rho_aba, d_ab]), rtol=1e-9)
    assert exact_inputs(direct, direct, ranges, config)[:, 0].max() < 1e-12, "no multipath: rho_ABA 0"
