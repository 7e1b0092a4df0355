"""The mixed-pixel benchmark's summary: one row per edge shape, plate range and albedo class, its counts the sums of
its scenes', its worst scene the one with the largest share of single depths more than 5 cm off; single depths are
the unresolved pixels' only, the earlier count (resolved pixels by their stronger return) beside them, and the
resolved pixels judged by their own target in its domain."""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest

from benchmarks.mixed_pixels import PER_SCENE_HEADER, PlateScene, SceneResult, per_scene_table, summary_table


def _result(mixed: int, single_far: int, ratios: tuple[float, ...] = (), far_resolved: int = 0,
            domain: tuple[int, int, int, int] = (0, 0, 0, 0), covered: int = 0) -> SceneResult:
    return SceneResult(mixed=mixed, single_far=single_far, single_far_noise=single_far // 2, surface_far=0.1,
                       flagged=mixed - single_far, resolved=len(ratios), inconsistent=0, near_errors=np.zeros(0),
                       far_errors=np.zeros(0), crb_ratios=np.asarray(ratios, float), far_resolved=far_resolved,
                       noise_expected=single_far / 4, domain_mixed=domain[0], domain_resolved=domain[1],
                       near_within=domain[2], far_within=domain[3], stated_covered=covered)


def _rows(lines: list[str]) -> dict[str, list[str]]:
    return {cells[0]: cells[1:] for cells in ([c.strip() for c in line.strip("|").split("|")] for line in lines[2:])}


@pytest.mark.unit
def test_summary_table__sums_a_group_and_names_its_worst_scene():
    results = [(PlateScene(5.0, 0.05, 5.5, 1.0), _result(60, 6, (0.4, 0.6), far_resolved=2)),
               (PlateScene(5.0, 0.5, 5.5, 0.5), _result(40, 0)),
               (PlateScene(5.0, 0.2, 7.0, 0.8), _result(40, 10, (1.0, 2.0, 3.5, 4.0), 1, (30, 2, 2, 1), 3)),
               (PlateScene(2.0, 0.05, 2.5, 1.0, edge_deg=45.0), _result(100, 0))]
    lines = summary_table(results)
    assert all(line.count("|") == lines[0].count("|") for line in lines)
    rows = _rows(lines)
    darker = rows["straight, plate at 5 m, darker plate"]
    # 16 of 100 mixed pixels; 3 sigmas 3 + 5; noise alone 1.5 + 2.5; the worst scene 10 of 40 (25 %) beats 6 of 60
    # (10 %); the earlier count adds the 3 resolved pixels whose stronger return is off.
    assert darker[:7] == ["2", "100", "16 (16.0 %)", "8", "4.0", "25.0 % (0.2 / 0.8, gap 2 m)", "19 (19.0 %)"]
    # 84 flagged, 6 resolved (2 + 4 returns' ratios), 2 of 30 in the domain, near 2 of 2, far 1 of 2, 3 of the 12
    # returns within their stated sigma; scenes' medians 0.5 and 2.75.
    assert darker[7:13] == ["84", "6", "0", "2 of 30", "100 % / 50 %", "25 %"]
    assert darker[13:] == ["0.50-2.75", "10 %"]
    equal = rows["straight, plate at 5 m, equal"]
    assert equal[2:5] == ["0 (0.0 %)", "0", "0.0"] and equal[5] == "-" and equal[10:13] == ["0 of 0", "- / -", "-"]
    assert list(rows)[-2] == "turned or wide, plate at 2 m, darker plate"
    assert rows["all"][:3] == ["4", "240", "16 (6.7 %)"] and rows["all"][6] == "19 (7.9 %)"


@pytest.mark.unit
def test_per_scene_table__a_resolved_pixel_is_not_a_single_depth():
    scene = PlateScene(2.0, 0.05, 5.0, 1.0)
    lines = per_scene_table([(scene, _result(63, 1, (0.5, 0.7, 2.0, 4.0), 2, (40, 2, 2, 1), 3))])
    assert lines[0] == PER_SCENE_HEADER and lines[2].count("|") == PER_SCENE_HEADER.count("|")
    cells = [c.strip() for c in lines[2].strip("|").split("|")]
    assert cells[2] == "63" and cells[3:10] == ["1 (2 %)", "0", "0.2", "3", "62", "4", "0"]
    assert cells[10:13] == ["2 of 40", "100 % / 50 %", "38 %"]


@pytest.mark.unit
def test_main__a_scene_text_matching_no_scene_is_one_usage_line_before_any_work(tmp_path):
    done = subprocess.run([sys.executable, "-m", "benchmarks.mixed_pixels", "--quick", "--scene", "no such plate",
                           "--work", str(tmp_path)], capture_output=True, text=True, timeout=120)
    assert done.returncode == 2 and done.stdout == ""
    assert "--scene 'no such plate' matches no plate scene" in done.stderr.splitlines()[-1]
    assert list(tmp_path.iterdir()) == []  # no model trained, nothing written
