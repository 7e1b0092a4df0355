"""The calibration and correction-diagnosis benchmarks at small sizes: their rows, their scenes' edges and
surfaces, and their command line."""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest

from mpi_lidar.config import Config
from mpi_lidar.simulation.scenes import corner, render


@pytest.mark.integration
def test_calibration_benchmark__quick_rows_compare_auto_with_the_true_footprint(tiny_geometric_model_dir):
    from benchmarks.calibration import run

    rows = run(str(tiny_geometric_model_dir), quick=True)
    assert len(rows) == 4 and {row["true_m2"] for row in rows} == {0.002, 0.041}
    for row in rows:
        assert row["auto_mm"] <= row["raw_mm"] + 0.05  # auto never does harm on these
    wall = [row for row in rows if not row["corner"]]
    assert all(row["auto_mm"] == row["raw_mm"] for row in wall)
    from benchmarks.calibration import HEADER, format_row

    assert {len(line.strip("|").split("|")) for line in [*HEADER.splitlines(), format_row(rows[0])]} == {13}
    # The rendered multipath removed exactly leaves the noise: at the strong footprint the edge comes down to
    # about the weak footprint's raw edge (the same corner with almost no multipath).
    weak, strong = (row for row in rows if row["corner"])
    assert strong["edge_removed_mm"] < 0.7 * strong["edge_raw_mm"]
    assert strong["edge_removed_mm"] == pytest.approx(weak["edge_raw_mm"], rel=0.25)


@pytest.mark.integration
def test_calibration_benchmark__a_chosen_scene_keeps_its_seed_and_an_unknown_one_is_refused(tmp_path):
    from benchmarks.calibration import chosen_cases, scene_cases

    whole = scene_cases(quick=False)
    chosen = chosen_cases(False, False, False, ("multi-object", "cylinder"))
    assert [label for _, (label, _, _) in chosen] == ["cylinder", "multi-object (Fig. 8)"]
    assert [index for index, _ in chosen] == [len(whole) - 2, len(whole) - 1]  # their seeds in the whole run
    with pytest.raises(ValueError, match="no scene of the set is named like 'tower'"):
        chosen_cases(False, False, False, ("tower",))
    result = subprocess.run([sys.executable, "-m", "benchmarks.calibration", "--model", str(tmp_path),
                             "--scene", "tower"], capture_output=True, text=True, check=False)
    assert result.returncode == 2
    assert result.stderr.strip().splitlines()[-1].startswith("benchmarks.calibration: no scene of the set")


@pytest.mark.integration
def test_calibration_benchmark__the_edge_region_follows_a_rolled_edge():
    from benchmarks.scenes import edge_line, edge_line_region

    upright = render(corner(90.0, 2.0, 0.8, height=24, width=32), Config(), np.random.default_rng(0))
    # The vertical edge: the pixels within 20 cm of the line x = 0, z = 2 m.
    upright_points = upright.reference_depth[..., None] * upright.rays()
    np.testing.assert_array_equal(edge_line_region(upright, edge_line(2.0)),
                                  np.hypot(upright_points[..., 0], upright_points[..., 2] - 2.0) <= 0.2)
    rolled = render(corner(90.0, 2.0, 0.8, height=24, width=32, roll_deg=90.0), Config(), np.random.default_rng(0))
    near = edge_line_region(rolled, edge_line(2.0, roll_deg=90.0))
    points = rolled.reference_depth[..., None] * rolled.rays()
    np.testing.assert_array_equal(near, np.hypot(points[..., 1], points[..., 2] - 2.0) <= 0.2)
    assert near.any() and not near.all()


@pytest.mark.integration
def test_calibration_benchmark__several_surfaces_edges_lie_where_two_surfaces_meet():
    from benchmarks.calibration import SEVERAL_SURFACES

    for label, factory, edges in SEVERAL_SURFACES:
        planes = [(np.asarray(r.centre), np.cross(r.half_u, r.half_v) / np.linalg.norm(np.cross(r.half_u, r.half_v)))
                  for r in factory().surfaces]
        for point, direction in edges:
            for along in (0.0, 0.3):
                x = point + along * direction
                on = [abs(normal @ (x - centre)) < 1e-9 for centre, normal in planes]
                assert sum(on) >= 2, f"{label}: an edge point on {sum(on)} surface planes"


@pytest.mark.integration
@pytest.mark.slow
def test_calibration_diagnosis__the_surfaces_beyond_the_view_carry_the_strong_multipath():
    from benchmarks.calibration_diagnosis import diagnose

    weak, strong = (diagnose(60, 2.4, 0.9, true_m2, seed=1, max_pixels=2_000) for true_m2 in (0.016, 0.1))
    for found, true_m2 in ((weak, 0.016), (strong, 0.1)):
        # Independent of the scan's blocks and planes: the exact surfaces against the reference depth.
        assert 1 / 1.5 <= found["exact, reference"].area_m2 / true_m2 <= 1.5
    assert 1 / 1.5 <= weak["shipped"].area_m2 / 0.016 <= 1.5, "weak multipath: the scan's own planes measure it"
    # Planes fitted to a narrow view, with partners only where the view sees them, take up the multipath.
    assert strong["exact, planes"].area_m2 < strong["exact, reference"].area_m2 / 2
    assert strong["shipped"].area_m2 > 0.1 / 1.5, "the partners continued beyond the view give it back"


@pytest.mark.unit
def test_correction_diagnosis__bins_the_edge_by_true_bias_on_the_true_surface(tiny_geometric_model):
    from benchmarks.correction_diagnosis import HEADER, diagnose, diagnosis_cases, format_row

    (label, scene, edges), = diagnosis_cases(quick=True)
    rows = diagnose(label, scene, edges, tiny_geometric_model, seed=0)
    assert len(rows) == 5 and sum(row["pixels"] for row in rows) > 500
    means = [row["bias_mm"] for row in rows]
    assert means == sorted(means) and means[-1] > 5.0
    for row in rows:
        # Each board of a 60-degree corner seen along its bisector meets the beam at 60 degrees.
        assert row["cos_i"] == pytest.approx(np.cos(np.deg2rad(60.0)), abs=0.08)
        assert all(np.isfinite(row[key]).all() for key in ("rho_aba", "d_ab_m", "taken_off_mm", "exact_inputs_mm"))
        assert format_row(row).count("|") == HEADER.splitlines()[0].count("|")


@pytest.mark.unit
def test_correction_diagnosis__a_scene_left_as_measured_gives_no_bins(tiny_geometric_model):
    from benchmarks.correction_diagnosis import diagnose
    from benchmarks.scenes import edge_line

    # A corner far weaker than the gate's threshold: no pixel near its edge is corrected.
    rows = diagnose("weak corner", corner(120.0, 2.0, 0.2, height=24, width=32), (edge_line(2.0),),
                    tiny_geometric_model, seed=0, true_m2=1e-5)
    assert rows == []
