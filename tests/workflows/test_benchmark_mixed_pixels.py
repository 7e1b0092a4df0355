"""The mixed-pixel benchmark's summary: one row per edge shape, plate range and albedo class, its counts the sums of
its scenes', its worst scene the one with the largest share of single depths more than 5 cm off."""

from __future__ import annotations

import numpy as np
import pytest

from benchmarks.mixed_pixels import PlateScene, SceneResult, summary_table


def _result(mixed: int, single_far: int, ratios: tuple[float, ...] = ()) -> SceneResult:
    return SceneResult(mixed=mixed, single_far=single_far, single_far_noise=single_far // 2, surface_far=0.1,
                       flagged=mixed - single_far, resolved=len(ratios), inconsistent=0, near_errors=np.zeros(0),
                       far_errors=np.zeros(0), crb_ratios=np.asarray(ratios, float))


def _rows(lines: list[str]) -> dict[str, list[str]]:
    return {cells[0]: cells[1:] for cells in ([c.strip() for c in line.strip("|").split("|")] for line in lines[2:])}


@pytest.mark.unit
def test_summary_table__sums_a_group_and_names_its_worst_scene():
    results = [(PlateScene(5.0, 0.05, 5.5, 1.0), _result(60, 6, (0.4, 0.6))),
               (PlateScene(5.0, 0.5, 5.5, 0.5), _result(40, 0)),
               (PlateScene(5.0, 0.2, 7.0, 0.8), _result(40, 10, (1.0,))),
               (PlateScene(2.0, 0.05, 2.5, 1.0, edge_deg=45.0), _result(100, 0))]
    rows = _rows(summary_table(results))
    darker = rows["straight, plate at 5 m, darker plate"]
    # 16 of 100 mixed pixels; the worst scene 10 of 40 (25 %) beats 6 of 60 (10 %); medians 0.5 and 1.0.
    assert darker[:5] == ["2", "100", "16 (16.0 %)", "8", "25.0 % (0.2 / 0.8, gap 2 m)"]
    assert darker[5:9] == ["84", "3", "0", "0.50-1.00"] and darker[9] == "10 %"
    assert rows["straight, plate at 5 m, equal"][2:4] == ["0 (0.0 %)", "0"]
    assert rows["straight, plate at 5 m, equal"][4] == "-" and rows["straight, plate at 5 m, equal"][8] == "-"
    assert list(rows)[-1] == "turned or wide, plate at 2 m, darker plate"
