"""The scene benchmark's comparison of the fused baseline with the raw one, at tiny sizes with a tiny model."""

from __future__ import annotations

import itertools
import math
import subprocess
import sys

import numpy as np
import pytest

from benchmarks.scenes import BASELINE_HEADER, DISTANCE_BINS_M, BaselineComparison, print_distance_error, scene_set
from tests.model_factory import tiny_model

NAN = math.nan


def _comparison(whole: tuple[float, float], masked: tuple[float, float]) -> BaselineComparison:
    return BaselineComparison({"whole map": whole, "masked": masked, "edge": (NAN, NAN)},
                              {"measured": 0.0, "fused": 1.0, "corrected": 0.0}, 0.68)


@pytest.mark.unit
def test_baseline_comparison__fused_must_be_no_worse_on_the_whole_map_and_the_mask():
    assert _comparison((1.2, 0.9), (1.1, 0.8)).fused_no_worse
    assert _comparison((1.2, 0.9), (NAN, NAN)).fused_no_worse, "a convex scene has no mask: the whole map decides"
    assert not _comparison((1.2, 0.9), (1.1, 1.2)).fused_no_worse
    assert not _comparison((1.2, 1.3), (1.1, 0.8)).fused_no_worse


def _distance_rows(printed: str) -> dict[str, list[str]]:
    rows = [line.strip("|").split("|") for line in printed.splitlines() if line.startswith("| ") and
            not line.startswith("| true")]
    return {cells[0].strip(): [cell.strip() for cell in cells[1:]] for cells in rows}


@pytest.mark.unit
def test_print_distance_error__median_robust_sd_and_outliers_per_true_distance_bin(capsys):
    rng = np.random.default_rng(4)
    true = np.concatenate([np.full(10_000, 0.07), np.full(10_000, 0.5), [np.nan]])
    error = np.concatenate([0.001 + 0.004 * rng.standard_normal(10_000), -0.02 + 0.05 * rng.standard_normal(10_000),
                            [0.0]])
    error[:100] = 0.5  # one pixel in a hundred took a wrong partner: the robust sd stays the core's
    print_distance_error(np.column_stack([true, true + error]))
    rows = _distance_rows(capsys.readouterr().out)
    assert list(rows) == [f"{lo:g}-{hi:g}" for lo, hi in itertools.pairwise(DISTANCE_BINS_M)] + ["0.6+"]
    near, far = rows["0.05-0.1"], rows["0.45-0.6"]
    assert float(near[0]) == pytest.approx(0.1, abs=0.02) and float(near[1]) == pytest.approx(0.4, rel=0.05)
    assert float(near[2]) == pytest.approx(1.0, abs=0.05) and near[3] == "10000"
    assert float(far[0]) == pytest.approx(-2.0, abs=0.15) and float(far[1]) == pytest.approx(5.0, rel=0.05)
    beyond_2_cm = 0.5 + 0.5 * math.erfc(0.8 / math.sqrt(2))  # N(-2, 5) cm: below -2 half, above +2 0.8 sd out
    assert float(far[2]) == pytest.approx(100 * beyond_2_cm, abs=1.5)
    assert rows["0-0.05"] == ["", "", "", "0"], "an empty bin is said, not skipped"


@pytest.mark.slow
@pytest.mark.integration
def test_scenes_benchmark__baselines_print_a_row_per_scene_with_shares_summing_to_100(tmp_path):
    model = tiny_model(tmp_path / "model")
    done = subprocess.run([sys.executable, "-m", "benchmarks.scenes", "--baselines", "--model", str(model),
                           "--shrink", "4"], capture_output=True, text=True, check=True, timeout=300)
    lines = done.stdout.splitlines()
    header = BASELINE_HEADER.splitlines()[0]
    table = lines[lines.index(header) + 2:]
    rows = [line.strip("|").split("|") for line in table[:table.index("")]]
    labels = [cells[0].strip() for cells in rows]
    assert labels[:-2] == [label for label, _, _ in scene_set()] and len(labels) == len(scene_set()) + 2
    assert {len(cells) for cells in rows} == {header.count("|") - 1}
    for cells in rows:
        shares = [float(share) for share in cells[6].split("/")]
        assert sum(shares) == pytest.approx(100.0, abs=0.2), f"{cells[0]}: shares {shares}"
        # A strong room shrunk to 12 x 16 pixels has no geometry to correct by: none of its errors within 1 sigma.
        assert 0.0 <= float(cells[7]) <= 100.0
    walls = [cells for cells in rows if cells[0].strip().startswith("flat wall")]
    for cells in walls:
        raw, fused = (float(mae) for mae in cells[2].split("/"))
        assert fused < 0.8 * raw, "a wall's pixels all fuse: four frequencies' noise instead of one"
        assert cells[4].strip() == "yes"
    summary = next(line for line in lines if line.startswith("fused <= raw"))
    assert summary.endswith(f"of {len(rows)} scenes")
