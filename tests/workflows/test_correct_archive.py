"""Batch correction: output directories from the stores' paths, truthful statuses, re-runs that keep numbers."""

from __future__ import annotations

import json
import re
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import zarr

from mpi_lidar.config import Config
from mpi_lidar.correction import CorrectionOptions, ScanOutcome, ScanStatus, correct_scan
from mpi_lidar.errors import MpiLidarError
from mpi_lidar.learning.model import load_model
from mpi_lidar.reporting.batch_report import batch_report, write_batch_report
from mpi_lidar.reporting.metrics import scan_metrics
from mpi_lidar.scans.scan import Scan
from mpi_lidar.scans.store import read_scan, write_scan
from mpi_lidar.simulation.scenes import flat_wall, render
from mpi_lidar.workflows.correct_archive import (
    correct_archive,
    failing_outcomes,
    process_scan,
    safe_scan_name,
    scan_output_paths,
)
from tests.cli_runner import assert_one_error_line, call_main
from tests.scan_factory import two_path_scan

# Every valid pixel corrected: a two-path scan ends 'corrected'. Amplitudes in V^2, given.
ALL = CorrectionOptions(gate="all", amplitude_scale=1.0)
# The command line's output level: what these tests read (corrected.zarr, metrics.json, report.md and .html);
# the figures and point clouds of "full" are tests/reporting's.
LIGHT = "light"


def saturated(scan: Scan, share: float) -> Scan:
    """The scan with about ``share`` of its pixels clipped at the brightest frequency's level, as a saturated
    detector clips them: a plateau of equal amplitudes."""
    level = np.float32(np.quantile(scan.amplitude[-1], 1.0 - share))
    amplitude = scan.amplitude.copy()
    amplitude[-1] = np.minimum(amplitude[-1], level)
    return replace(scan, amplitude=amplitude)


def corrected_depth(output: Path) -> np.ndarray:
    return zarr.open_group(str(output / "corrected.zarr"), mode="r")["corrected_depth"][:]


# --- where the outputs go --------------------------------------------------------------------------------


@pytest.mark.slow
@pytest.mark.integration
def test_correct_archive__same_named_scans_in_day_folders_both_survive(small_model, tmp_path):
    archive = tmp_path / "archive"
    for seed, day in enumerate(("day1", "day2")):
        write_scan(two_path_scan("frame", seed=seed), archive / day / "frame.scan.zarr")
    out = tmp_path / "out"
    outcomes = correct_archive([str(archive / "*" / "*.scan.zarr")], small_model, out, ALL, outputs=LIGHT)
    assert [(o.name, o.status, o.output) for o in outcomes] == [
        ("frame", "corrected", str(out / "day1" / "frame")), ("frame", "corrected", str(out / "day2" / "frame"))]
    first, second = corrected_depth(out / "day1" / "frame"), corrected_depth(out / "day2" / "frame")
    assert not np.array_equal(first, second), "each day keeps its own result"
    alone = correct_archive([str(archive / "day2" / "frame.scan.zarr")], small_model, tmp_path / "alone", ALL,
                            outputs=LIGHT)
    assert alone[0].output == str(tmp_path / "alone" / "frame"), "a single scan keeps its store's name"
    np.testing.assert_array_equal(corrected_depth(tmp_path / "alone" / "frame"), second)
    summary = batch_report(outcomes, 1.0).markdown()
    for day in ("day1", "day2"):
        assert f"`{archive / day / 'frame.scan.zarr'}`" in summary, "each source is listed"
    assert summary.count("| frame | corrected |") == 2, "the scan's own name is kept"


@pytest.mark.integration
def test_correct_archive__two_inputs_for_one_output_are_refused_with_nothing_written(small_model, tmp_path):
    archive = tmp_path / "archive"
    write_scan(two_path_scan("one"), archive / "frame.scan.zarr")
    write_scan(two_path_scan("two"), archive / "frame.zarr")
    out = tmp_path / "out"
    with pytest.raises(MpiLidarError) as refused:
        correct_archive([str(archive / "frame.scan.zarr"), str(archive / "frame.zarr")], small_model, out, ALL)
    message = str(refused.value)
    assert "\n" not in message and "frame.scan.zarr" in message and str(archive / "frame.zarr") in message
    assert not out.exists(), "refused before anything is written"
    write_scan(two_path_scan("inner"), archive / "frame" / "inner.scan.zarr")
    with pytest.raises(MpiLidarError, match="inside the outputs of"):
        scan_output_paths([str(archive / "frame.scan.zarr"), str(archive / "frame" / "inner.scan.zarr")])


@pytest.mark.integration
def test_correct_cli__collision_is_one_error_line_exit_2(small_model, tmp_path, monkeypatch, capsys):
    for day in ("day1", "day2"):
        write_scan(two_path_scan("frame"), tmp_path / day / "frame.scan.zarr")
    write_scan(two_path_scan("frame"), tmp_path / "day1" / "frame.zarr")
    code, _out, err = call_main(monkeypatch, capsys, "correct", tmp_path / "day1" / "frame.scan.zarr",
                                tmp_path / "day1" / "frame.zarr", tmp_path / "day2" / "frame.scan.zarr",
                                "--model", small_model, "--out", tmp_path / "out", "--workers", "0")
    assert code == 2 and err.count("\n") == 1 and err.startswith("error: scans ")
    assert not (tmp_path / "out").exists()


@pytest.mark.integration
def test_correct_archive__scan_named_summary_and_the_summary_both_survive(small_model, tmp_path):
    archive = tmp_path / "archive"
    write_scan(two_path_scan("summary"), archive / "summary.scan.zarr")
    write_scan(two_path_scan("other", seed=1), archive / "other.scan.zarr")
    out = tmp_path / "out"
    outcomes = correct_archive([str(archive)], small_model, out, ALL, outputs=LIGHT)
    write_batch_report(outcomes, 1.0, out)
    assert sorted(p.name for p in out.iterdir()) == ["other", "summary", "summary.scan"]
    assert (out / "summary" / "report.md").read_text().startswith("# Batch correction")
    assert (out / "summary.scan" / "report.md").read_text().startswith("# Correction of summary")
    assert json.loads((out / "summary.scan" / "metrics.json").read_text())["scan"] == "summary"
    again = correct_archive([str(archive)], small_model, out, ALL, outputs=LIGHT)
    assert [o.status for o in again] == ["skipped", "skipped"], "found again where it was written"
    write_batch_report(again, 1.0, out)
    assert (out / "summary.scan" / "corrected.zarr").is_dir()


@pytest.mark.unit
def test_safe_scan_name__a_final_newline_is_refused():
    assert safe_scan_name("frame-1.b") == "frame-1.b"
    for name in ("frame\n", "frame\r\n", "\nframe", "../x", ".hidden", "a/b", "", "x" * 129):
        with pytest.raises(MpiLidarError, match="not a safe directory name"):
            safe_scan_name(name)


@pytest.mark.integration
def test_process_scan__name_with_trailing_newline_fails_that_scan_alone(small_model, tmp_path):
    archive = tmp_path / "archive"
    bad = write_scan(two_path_scan("frame"), archive / "frame.scan.zarr")
    zarr.open_group(str(bad), mode="r+").attrs["name"] = "frame\n"
    write_scan(two_path_scan("good"), archive / "good.scan.zarr")
    out = tmp_path / "out"
    by_source = {o.source: o for o in correct_archive([str(archive)], small_model, out, ALL, outputs=LIGHT)}
    failed = by_source[str(bad)]
    assert failed.status == "failed" and "not a safe directory name" in failed.reason and "\n" not in failed.reason
    assert by_source[str(archive / "good.scan.zarr")].status == "corrected"
    assert sorted(p.name for p in out.iterdir()) == ["good"]


# --- re-runs ---------------------------------------------------------------------------------------------


@pytest.mark.integration
def test_correct_archive__rerun_keeps_the_numbers_in_the_summary(small_model, tmp_path):
    archive = tmp_path / "archive"
    for seed, name in enumerate(("a", "b")):
        write_scan(replace(two_path_scan(name, seed=seed), azimuth_rad=None, elevation_rad=None),
                   archive / f"{name}.scan.zarr")
    out = tmp_path / "out"
    first = correct_archive([str(archive)], small_model, out, ALL)  # full: its no-geometry note on point clouds
    second = correct_archive([str(archive)], small_model, out, ALL)
    assert [o.status for o in first] == ["corrected"] * 2 and [o.status for o in second] == ["skipped"] * 2
    for before, after in zip(first, second, strict=True):
        assert after.counts == before.counts and after.counts["corrected"] > 0
        assert after.metrics == before.metrics, "JSON keeps every digit"
        assert after.notes == before.notes and after.notes, "the no-geometry notes come back too"
        assert after.kept_status == "corrected" and after.effective_status == "corrected"

    def rows(outcomes: list[ScanOutcome]) -> list[list[str]]:
        table = [line.split(" | ") for line in batch_report(outcomes, 1.0).markdown().splitlines()
                 if line.startswith("| a |") or line.startswith("| b |")]
        return [row[2:8] for row in table]  # gated out, invalid and the four MAE columns

    assert rows(second) == rows(first) and all(cell for row in rows(second) for cell in row[2:])
    summary = batch_report(second, 1.0).markdown()
    assert "2 scans in 1.0 s: 0 corrected, 0 unchanged, 0 degraded, 0 unserved, 2 already done, 0 failed." in summary
    assert "already corrected with this model and options (corrected)" in summary


@pytest.mark.integration
def test_correct_archive__damaged_metrics_json_is_corrected_again(small_model, tmp_path):
    write_scan(two_path_scan("a"), tmp_path / "a.scan.zarr")
    out = tmp_path / "out"
    correct_archive([str(tmp_path / "a.scan.zarr")], small_model, out, ALL, outputs=LIGHT)
    (out / "a" / "metrics.json").write_text("{not json")
    [again] = correct_archive([str(tmp_path / "a.scan.zarr")], small_model, out, ALL, outputs=LIGHT)
    assert again.status == "corrected" and json.loads((out / "a" / "metrics.json").read_text())["counts"]


# --- statuses --------------------------------------------------------------------------------------------


@pytest.mark.integration
def test_process_scan__flat_scan_is_unchanged(small_model, tmp_path):
    write_scan(render(flat_wall(20.0, height=24, width=32), Config(), np.random.default_rng(1)),
               tmp_path / "wall.scan.zarr")
    outcome = process_scan(tmp_path / "wall.scan.zarr", small_model, tmp_path / "out", CorrectionOptions(),
                           outputs=LIGHT)
    assert outcome.status == ScanStatus.UNCHANGED and outcome.counts["corrected"] == 0
    assert outcome.counts["no_multipath"] > 0 and outcome.metrics["whole map"]["pixels"] > 0
    assert (tmp_path / "out" / "wall" / "report.html").is_file(), "valid outputs are still written"
    assert "0 corrected, 1 unchanged" in batch_report([outcome], 1.0).markdown()


@pytest.mark.integration
def test_process_scan__mostly_saturated_scan_is_degraded(small_model, tmp_path):
    write_scan(saturated(two_path_scan("hot"), 0.62), tmp_path / "hot.scan.zarr")
    outcome = process_scan(tmp_path / "hot.scan.zarr", small_model, tmp_path / "out", ALL, outputs=LIGHT)
    share = outcome.counts["saturated"] / sum(outcome.counts.values())
    assert 0.55 < share < 0.7 and outcome.counts["corrected"] > 0
    assert outcome.status == ScanStatus.DEGRADED
    assert (tmp_path / "out" / "hot" / "corrected.zarr").is_dir()
    assert "| hot | ⚠ degraded |" in batch_report([outcome], 1.0).markdown()
    lenient = ALL.model_copy(update={"max_invalid_share": 0.8})
    assert lenient.sha256() == ALL.sha256(), "the threshold never changes a pixel, so not the identity"
    again = process_scan(tmp_path / "hot.scan.zarr", small_model, tmp_path / "out", lenient, outputs=LIGHT)
    assert again.status == "skipped" and again.kept_status == "corrected", "re-classified, not re-corrected"


def near_end_scan(model_dir: Path, name: str) -> Scan:
    """A two-path wall at 70 % of the model's nearest trained range: out of its range, multipath in half."""
    low = load_model(model_dir).card.dataset.prior.d_as_m[0]
    return two_path_scan(name, near_m=0.7 * low, albedo=0.3)


@pytest.mark.integration
def test_process_scan__scan_out_of_the_models_range_is_unserved_with_its_reason(small_model, tmp_path):
    write_scan(near_end_scan(small_model, "near"), tmp_path / "near.scan.zarr")
    outcome = process_scan(tmp_path / "near.scan.zarr", small_model, tmp_path / "out", ALL, outputs=LIGHT)
    assert outcome.status == ScanStatus.UNSERVED and outcome.unserved == "out_of_range"
    assert outcome.counts["corrected"] == 0 and outcome.counts["out_of_range"] > 0
    assert "mpi-lidar pipeline" in outcome.reason
    recorded = json.loads((tmp_path / "out" / "near" / "metrics.json").read_text())["unserved"]
    assert recorded["reason"] == "out_of_range" and recorded["message"] == outcome.reason
    assert "| near | ⚠ unserved |" in batch_report([outcome], 1.0).markdown()
    again = process_scan(tmp_path / "near.scan.zarr", small_model, tmp_path / "out", ALL, outputs=LIGHT)
    assert again.status == "skipped" and again.kept_status == "unserved" and again.unserved == "out_of_range"


@pytest.mark.integration
def test_process_scan__flat_wall_out_of_range_that_needs_nothing_stays_unchanged(small_model, tmp_path):
    wall = two_path_scan("wall", multipath=False, near_m=0.7 * load_model(small_model).card.dataset.prior.d_as_m[0],
                         albedo=0.3)
    write_scan(wall, tmp_path / "flat.scan.zarr")
    outcome = process_scan(tmp_path / "flat.scan.zarr", small_model, tmp_path / "out", CorrectionOptions(),
                           outputs=LIGHT)
    assert outcome.status == ScanStatus.UNCHANGED and outcome.unserved is None
    assert outcome.counts["out_of_range"] == 0 and outcome.counts["no_multipath"] > 0


@pytest.mark.integration
def test_process_scan__amplitudes_in_another_unit_are_unserved_not_degraded(small_model, tmp_path):
    scan = two_path_scan("counts")
    write_scan(replace(scan, amplitude=(scan.amplitude * 4000).astype(np.float32)), tmp_path / "counts.scan.zarr")
    outcome = process_scan(tmp_path / "counts.scan.zarr", small_model, tmp_path / "out", ALL, outputs=LIGHT)
    assert outcome.status == ScanStatus.UNSERVED and outcome.unserved == "amplitude_units"
    assert "--sensor" in outcome.reason
    auto = process_scan(tmp_path / "counts.scan.zarr", small_model, tmp_path / "auto",
                        ALL.model_copy(update={"amplitude_scale": "auto"}), outputs=LIGHT)
    # no unit is read from the scan: the model is not applied, the fused depths are written
    assert auto.status == ScanStatus.UNSERVED and auto.unserved == "amplitude_units"
    assert auto.counts["corrected"] == 0 and auto.counts["saturated"] == 0
    fused = zarr.open_group(str(tmp_path / "auto" / "counts" / "corrected.zarr"), mode="r")["estimate"][:]
    assert (fused == 2).mean() > 0.9, "fused depths, as in V^2"


@pytest.mark.integration
def test_correct_cli__unserved_scan_exits_1_unless_allowed(small_model, tmp_path, monkeypatch, capsys):
    archive = tmp_path / "archive"
    write_scan(near_end_scan(small_model, "near"), archive / "near.scan.zarr")
    write_scan(two_path_scan("fine", seed=1), archive / "fine.scan.zarr")
    arguments = ["correct", archive, "--model", small_model, "--gate", "all", "--workers", "0"]
    code, out, err = call_main(monkeypatch, capsys, *arguments, "--out", tmp_path / "strict")
    assert code == 1 and re.search(r"^near +unserved ", out, re.M) and re.search(r"^fine +corrected ", out, re.M)
    assert err.startswith(f"error: scan {archive / 'near.scan.zarr'}: unserved (out_of_range): ")
    assert len(err.splitlines()) == 1 and "mpi-lidar pipeline" in err
    code, out, err = call_main(monkeypatch, capsys, *arguments, "--out", tmp_path / "lenient", "--allow-unserved")
    assert code == 0 and err == "" and ": 1 corrected, 1 unserved" in out


@pytest.mark.integration
def test_correct_cli__fail_on_degraded_exits_1_after_writing_the_summary(small_model, tmp_path, monkeypatch,
                                                                          capsys):
    archive = tmp_path / "archive"
    write_scan(saturated(two_path_scan("hot"), 0.62), archive / "hot.scan.zarr")
    write_scan(two_path_scan("fine", seed=1), archive / "fine.scan.zarr")
    arguments = ["correct", archive, "--model", small_model, "--gate", "all", "--workers", "0", "--amplitude-scale",
                 "1"]

    code, out, err = call_main(monkeypatch, capsys, *arguments, "--out", tmp_path / "plain")
    assert code == 0 and err == "" and re.search(r"^hot +degraded ", out, re.M)
    assert re.search(r"^fine +corrected ", out, re.M)
    assert "2 scans in " in out and ": 1 corrected, 1 degraded\n" in out

    code, out, err = call_main(monkeypatch, capsys, *arguments, "--out", tmp_path / "strict",
                               "--fail-on", "degraded", "--fail-on", "unchanged")
    assert code == 1
    assert len(err.splitlines()) == 1 and re.fullmatch(
        rf"error: scan {re.escape(str(archive / 'hot.scan.zarr'))}: degraded: 6[12]\.\d % of its pixels are invalid, "
        r"first saturated \(6[12]\.\d %: its amplitude is saturated\)",
        err.splitlines()[0]), err
    summary = (tmp_path / "strict" / "summary" / "report.md").read_text()
    assert re.search(r"^\| hot \|[^\n]*\| ⚠ degraded \|", summary, re.M)
    assert (tmp_path / "strict" / "fine" / "report.html").is_file()

    code, _out, err = call_main(monkeypatch, capsys, *arguments, "--out", tmp_path / "strict",
                                "--fail-on", "degraded")
    assert code == 1 and "degraded" in err and "existing outputs" in err, "a re-run fails as the first did"
    code, _out, _err = call_main(monkeypatch, capsys, *arguments, "--out", tmp_path / "strict",
                                 "--max-invalid-share", "0.9", "--fail-on", "degraded")
    assert code == 0, "a lenient threshold re-classifies the kept outputs"


@pytest.mark.unit
def test_failing_outcomes__failed_always_fails_and_unknown_statuses_are_refused():
    outcomes = [ScanOutcome("a", "a", ScanStatus.FAILED, "broken"), ScanOutcome("b", "b", ScanStatus.UNCHANGED),
                ScanOutcome("c", "c", ScanStatus.SKIPPED, kept_status=ScanStatus.DEGRADED)]
    assert [o.source for o in failing_outcomes(outcomes)] == ["a"]
    assert [o.source for o in failing_outcomes(outcomes, ["unchanged", "degraded"])] == ["a", "b", "c"]
    with pytest.raises(MpiLidarError, match="fail_on takes degraded, unchanged, failed"):
        failing_outcomes(outcomes, ["corrected"])


# --- one bad scan ----------------------------------------------------------------------------------------


@pytest.mark.integration
@pytest.mark.filterwarnings("ignore:Pydantic serializer warnings:UserWarning")
def test_process_scan__unexpected_exception_type_fails_that_scan_alone(small_model, tmp_path):
    archive = tmp_path / "archive"
    write_scan(two_path_scan("geometry"), archive / "geometry.scan.zarr")
    write_scan(replace(two_path_scan("plain", seed=1), azimuth_rad=None, elevation_rad=None),
               archive / "plain.scan.zarr")
    # Unvalidated options with a text footprint: only a scan with geometry computes the coupling with it,
    # and numpy raises a TypeError (UFuncTypeError) deep inside the gate: not a library error, nor an
    # OSError, ValueError or KeyError.
    options = CorrectionOptions.model_construct(**{**CorrectionOptions().model_dump(), "footprint_area_m2": "wide"})
    outcomes = {o.name: o for o in correct_archive([str(archive)], small_model, tmp_path / "out", options,
                                                              outputs=LIGHT)}
    broken = outcomes["geometry.scan.zarr"]
    assert broken.status == "failed" and re.fullmatch(r"UFuncTypeError: ufunc 'multiply' .+", broken.reason)
    assert outcomes["plain"].status == "corrected" and (tmp_path / "out" / "plain" / "report.html").is_file()
    assert not (tmp_path / "out" / "geometry").exists()


# --- work beside the correction ----------------------------------------------------------------------------


@pytest.mark.integration
@pytest.mark.parametrize("kept_in_store", [False, True], ids=["in-memory", "in-store"])
@pytest.mark.parametrize("outputs", ["light", "data"])
def test_process_scan__identity_and_metrics_made_beside_are_those_made_alone(small_model, tmp_path, monkeypatch,
                                                                              kept_in_store, outputs):
    source = write_scan(two_path_scan("beside"), tmp_path / "beside.scan.zarr")
    if kept_in_store:  # the scan's maps stay in the store: hashed and measured before, not beside
        monkeypatch.setattr("mpi_lidar.workflows.correct_archive.STORED_MAPS_ABOVE_BYTES", 0)
    outcome = process_scan(source, small_model, tmp_path / "out", ALL, outputs=outputs)
    assert outcome.status == "corrected", outcome.reason
    scan = read_scan(source)
    expected = json.loads(json.dumps(scan_metrics(scan, correct_scan(scan, load_model(small_model), ALL))))
    assert expected["whole map"]["pixels"] > 0
    assert json.loads(json.dumps(outcome.metrics)) == expected
    assert json.loads((Path(outcome.output) / "metrics.json").read_text())["metrics"] == expected
    attrs = zarr.open_group(str(Path(outcome.output) / "corrected.zarr"), mode="r").attrs
    assert attrs["scan_sha256"] == scan.content_sha256()
    assert (Path(outcome.output) / "thumbnail.png").is_file() == (outputs == "light")
    [again] = correct_archive([str(source)], small_model, tmp_path / "out", ALL, outputs=outputs)
    assert again.status == "skipped", "the identity written beside the correction is the one a re-run finds"


def with_npz(root: Path) -> Path:
    """``root`` with another tool's file in it."""
    (root / "frame.npz").write_bytes(b"")
    return root


@pytest.mark.integration
@pytest.mark.parametrize("make, fragment", [
    (lambda root: root / "missing.scan.zarr", "does not exist"),
    (lambda root: root, "holds no *.scan.zarr store"),
    (lambda root: with_npz(root) / "frame.npz", "mpi-lidar import-scan"),
    (lambda root: with_npz(root), "mpi-lidar import-scan"),
    (lambda root: str(root / "*.scan.zarr"), "matches no scan store"),
], ids=["missing", "empty-folder", "npz-file", "npz-folder", "empty-glob"])
def test_correct_cli__nothing_to_correct_is_one_line_exit_2_and_nothing_written(tmp_path, monkeypatch, capsys,
                                                                               small_model, make, fragment):
    root = tmp_path / "in"
    root.mkdir()
    code, out, err = call_main(monkeypatch, capsys, "correct", make(root), "--model", small_model,
                               "--out", tmp_path / "out", "--workers", "0")
    assert code == 2 and out == ""
    assert_one_error_line(err, fragment)
    assert not (tmp_path / "out").exists()
