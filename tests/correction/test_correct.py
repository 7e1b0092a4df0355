from __future__ import annotations

import re
from dataclasses import replace

import numpy as np
import pytest
import zarr
from click.testing import CliRunner

from mpi_lidar.cli import cli
from mpi_lidar.config import Config, SimulatorConfig
from mpi_lidar.correction import NO_GEOMETRY_NOTE, CorrectionOptions, Flag, ScanStatus, correct_scan
from mpi_lidar.correction.options import Estimate
from mpi_lidar.errors import MpiLidarError
from mpi_lidar.learning.model import load_model
from mpi_lidar.reporting.correction_notes import correction_notes
from mpi_lidar.scans.scan import Scan
from mpi_lidar.scans.store import write_scan
from mpi_lidar.simulation.scenes import corner, flat_wall, render
from mpi_lidar.workflows.correct_archive import correct_archive, process_scan
from tests.cli_runner import call_main
from tests.scan_factory import inverse_variance_mean, two_path_scan

# The command line's output level: what these tests read (corrected.zarr, metrics.json, report.md); the figures
# and point clouds of "full" are tests/reporting's.
LIGHT = "light"


@pytest.fixture(scope="module")
def archive(tmp_path_factory):
    root = tmp_path_factory.mktemp("archive")
    for index, name in enumerate(("a", "b", "c")):
        write_scan(two_path_scan(name, seed=index), root / f"{name}.scan.zarr")
    return root


def damaged(scan: Scan) -> Scan:
    """Pixel (0,0) NaN, (0,1) no return, (0,2) saturated, (0,3) one frequency off by a wrap."""
    depth, amplitude = scan.depth.copy(), scan.amplitude.copy()
    depth[1, 0, 0] = np.nan
    amplitude[:, 0, 1] = 1e-7
    amplitude[:, 0, 2] = 5.0
    depth[0, 0, 3] += 1.0
    return replace(scan, depth=depth, amplitude=amplitude)


@pytest.mark.unit
def test_correct_scan__flags_say_what_was_done(pixelwise_model):
    options = CorrectionOptions(gate="all", saturation_amplitude_v2=0.7176)  # a threshold given, as a profile does
    correction = correct_scan(damaged(two_path_scan("d")), load_model(pixelwise_model), options)
    assert [correction.flags[0, j] for j in range(4)] == [Flag.NOT_FINITE, Flag.NO_RETURN, Flag.SATURATED,
                                                         Flag.INCONSISTENT]
    assert np.isnan(correction.depth[0, :4]).all()
    assert (correction.flags[1:] == Flag.CORRECTED).all()
    assert np.isfinite(correction.depth[1:]).all()
    assert correction.counts()["corrected"] == 24 * 32 - 4


@pytest.mark.unit
def test_correct_scan__corrected_pixels_are_the_model_prediction(pixelwise_model):
    scan = two_path_scan("p")
    model = load_model(pixelwise_model)
    correction = correct_scan(scan, model, CorrectionOptions(gate="all", tile_pixels=100))
    np.testing.assert_allclose(correction.depth.ravel(), model.predict_depth(scan.raw_pixels()), atol=1e-6)


@pytest.mark.unit
def test_correct_scan__multipath_region_improves(pixelwise_model):
    scan = two_path_scan("m", height=40, width=40)
    correction = correct_scan(scan, load_model(pixelwise_model), CorrectionOptions(gate="all"))
    left = np.s_[:, :20]  # the multipath half
    raw_error = np.abs(scan.depth[-1][left] - scan.reference_depth[left]).mean()
    corrected_error = np.abs(correction.depth[left] - scan.reference_depth[left]).mean()
    assert corrected_error < 0.7 * raw_error


@pytest.mark.unit
def test_consistency_gate__skips_about_all_pixels_without_multipath(pixelwise_model):
    scan = two_path_scan("clean", height=60, width=60, multipath=False)
    correction = correct_scan(scan, load_model(pixelwise_model), CorrectionOptions(gate="consistency", baseline="raw"))
    skipped = (correction.flags == Flag.NOT_NEEDED).mean()
    assert skipped > 0.97  # chi^2 at p = 0.01: about 1 % false alarms
    untouched = correction.flags == Flag.NOT_NEEDED
    np.testing.assert_array_equal(correction.depth[untouched], scan.depth[-1][untouched])


@pytest.mark.unit
def test_correct_scan__other_frequencies_are_refused(pixelwise_model):
    scan = two_path_scan("f")
    three = replace(scan, frequencies_hz=scan.frequencies_hz[1:], depth=scan.depth[1:], amplitude=scan.amplitude[1:])
    with pytest.raises(MpiLidarError, match=r"model expects 12\.5, 18\.75, 25, 31\.25 MHz"):
        correct_scan(three, load_model(pixelwise_model), CorrectionOptions())


@pytest.mark.unit
def test_correct_archive__rerun_skips_finished_scans_and_redoes_missing(archive, pixelwise_model, tmp_path):
    first = correct_archive([str(archive)], pixelwise_model, tmp_path, CorrectionOptions(), outputs=LIGHT)
    assert [o.status for o in first] == ["unchanged"] * 3, "a tilted plane: the geometry gate corrects nothing"
    stamp = (tmp_path / "a" / "corrected.zarr" / "zarr.json").stat().st_mtime_ns
    import shutil

    shutil.rmtree(tmp_path / "b")  # as if the batch had been interrupted before scan b
    second = correct_archive([str(archive)], pixelwise_model, tmp_path, CorrectionOptions(), outputs=LIGHT)
    assert [o.status for o in second] == ["skipped", "unchanged", "skipped"]
    assert (tmp_path / "a" / "corrected.zarr" / "zarr.json").stat().st_mtime_ns == stamp
    with pytest.raises(MpiLidarError, match="corrected with other settings"):
        correct_archive([str(archive / "a.scan.zarr")], pixelwise_model, tmp_path,
                        CorrectionOptions(gate="consistency"), outputs=LIGHT)
    other_gate = correct_archive([str(archive / "a.scan.zarr")], pixelwise_model, tmp_path,
                                 CorrectionOptions(gate="consistency"), outputs=LIGHT, replace_options=True)
    assert other_gate[0].status == "corrected", "other options are another correction"
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".")], "no staging directories left"


@pytest.mark.unit
def test_correct_archive__leftovers_of_a_killed_batch_are_removed_and_nothing_else(archive, pixelwise_model, tmp_path):
    leftovers = [tmp_path / ".a.writing-0123abcd", tmp_path / ".b.old-89abcdef"]
    for path in leftovers:
        (path / "corrected.zarr").mkdir(parents=True)
    kept = [tmp_path / ".user-notes", tmp_path / ".a.writing-not-hex"]
    for path in kept:
        path.mkdir()
    correct_archive([str(archive / "a.scan.zarr")], pixelwise_model, tmp_path, CorrectionOptions(gate="all"),
                    outputs=LIGHT)
    assert not any(path.exists() for path in leftovers)
    assert all(path.is_dir() for path in kept)


@pytest.mark.integration
def test_correct_archive__dask_and_in_process_agree(archive, pixelwise_model, tmp_path, cluster_client):
    outcomes = correct_archive([str(archive / "*.scan.zarr")], pixelwise_model, tmp_path / "dask", CorrectionOptions(),
                               client=cluster_client, outputs=LIGHT)
    local = correct_archive([str(archive)], pixelwise_model, tmp_path / "local", CorrectionOptions(), outputs=LIGHT)
    assert [o.status for o in outcomes] == ["unchanged"] * 3
    for name in ("a", "b", "c"):
        on_dask = zarr.open_group(str(tmp_path / "dask" / name / "corrected.zarr"), mode="r")["corrected_depth"][:]
        here = zarr.open_group(str(tmp_path / "local" / name / "corrected.zarr"), mode="r")["corrected_depth"][:]
        np.testing.assert_array_equal(on_dask, here)
    assert [o.metrics for o in outcomes] == [o.metrics for o in local]


@pytest.mark.unit
def test_process_scan__bad_scans_fail_alone_with_a_reason(tmp_path, pixelwise_model, archive):
    bad = tmp_path / "bad.scan.zarr"
    bad.mkdir()
    (bad / "zarr.json").write_text("{not json")
    escaping = two_path_scan("../escape")
    group_path = tmp_path / "escape.scan.zarr"
    write_scan(replace(escaping, name="fine"), group_path)
    zarr.open_group(str(group_path), mode="r+").attrs["name"] = "../escape"
    outcomes = correct_archive([str(bad), str(group_path), str(archive / "a.scan.zarr")], pixelwise_model,
                               tmp_path / "out", CorrectionOptions(), outputs=LIGHT)
    by_name = {o.source: o for o in outcomes}
    assert by_name[str(bad)].status == "failed" and "not a readable Zarr store" in by_name[str(bad)].reason
    escaped = by_name[str(group_path)]
    assert escaped.status == "failed" and "not a safe directory name" in escaped.reason
    good = by_name[str(archive / "a.scan.zarr")]
    assert good.status == "unchanged"
    # inputs from two folders: outputs are named by their path below the folders' common root
    assert good.output == str(tmp_path / "out" / archive.name / "a")
    assert sorted(p.name for p in (tmp_path / "out").iterdir()) == [archive.name]
    assert not (tmp_path / "escape").exists() and not list((tmp_path / "out").rglob("escape"))


@pytest.mark.unit
def test_process_scan__unwritable_output_fails_cleanly(pixelwise_model, archive):
    outcome = process_scan(archive / "a.scan.zarr", pixelwise_model, "/proc/self/forbidden", CorrectionOptions())
    assert outcome.status == "failed" and outcome.reason


@pytest.mark.integration
@pytest.mark.slow
def test_correct_cli__batch_with_a_failure_exits_non_zero_and_writes_summary(archive, pixelwise_model, tmp_path,
                                                                           monkeypatch, capsys):
    bad = tmp_path / "broken.scan.zarr"
    bad.mkdir()
    code, stdout, stderr = call_main(monkeypatch, capsys, "correct", archive / "a.scan.zarr", bad, "--model",
                                     pixelwise_model, "--out", tmp_path / "out", "--workers", 0, "--outputs", "full")
    assert code == 1
    errors = [line for line in stderr.splitlines() if line.startswith("error:")]
    assert len(errors) == 1 and "broken.scan.zarr" in errors[0]
    assert re.search(r"^a +unchanged ", stdout, re.M)
    assert (tmp_path / "out" / "summary" / "report.html").exists()
    for name in ("maps.png", "error_hist.png", "point_cloud.png", "raw.ply", "corrected.ply", "report.md"):
        assert (tmp_path / "out" / archive.name / "a" / name).exists(), name  # two folders: nested


@pytest.mark.unit
def test_correct_cli__missing_model_is_one_line_exit_2(archive, tmp_path, monkeypatch, capsys):
    code, _, stderr = call_main(monkeypatch, capsys, "correct", archive, "--model", tmp_path / "nope", "--out",
                                tmp_path / "out", "--workers", 0)
    assert code == 2
    assert stderr.strip().count("\n") == 0 and stderr.startswith("error:")
    assert not (tmp_path / "out").exists()


# --- the geometry gate ------------------------------------------------------------------------------------


@pytest.mark.unit
def test_geometry_gate__flat_wall_is_left_exactly_as_measured(pixelwise_model):
    scan = render(flat_wall(20.0, height=48, width=64), Config(), np.random.default_rng(1))
    model = load_model(pixelwise_model)
    correction = correct_scan(scan, model, CorrectionOptions())
    valid = ~np.isin(correction.flags, [Flag.NOT_FINITE, Flag.NO_RETURN, Flag.SATURATED, Flag.INCONSISTENT])
    assert (correction.flags[valid] == Flag.NO_MULTIPATH).mean() > 0.99
    gated = correction.flags == Flag.NO_MULTIPATH
    fused = correction.estimate == Estimate.FUSED
    assert fused[gated].mean() > 0.99, "a flat wall's frequencies agree within noise: nearly every pixel is fused"
    assert correction.frequency_offsets_m is not None, "a flat wall measures its frequencies' offsets"
    assert correction.window_leakage_removed, "the simulator's window leaks"
    expected = inverse_variance_mean(scan, correction.frequency_offsets_m, window=True)
    np.testing.assert_allclose(correction.depth[fused], expected[fused], rtol=0, atol=2e-6)
    raw_mae = np.abs(scan.depth[-1] - scan.reference_depth)[valid].mean()
    corrected_mae = np.abs(correction.depth - scan.reference_depth)[valid].mean()
    assert corrected_mae <= 0.8 * raw_mae, "four frequencies fused: about 0.7 of the highest one's noise"
    raw = correct_scan(scan, model, CorrectionOptions(baseline="raw"))
    np.testing.assert_array_equal(raw.depth[gated], scan.depth[-1][gated])
    assert (raw.estimate[gated] == Estimate.MEASURED).all()
    pixelwise = correct_scan(scan, model, CorrectionOptions(gate="all"))
    assert (pixelwise.flags[valid] == Flag.CORRECTED).all()
    assert correction.multipath_bias_m is not None and float(correction.multipath_bias_m.max()) == 0.0
    notes = correction_notes(correction)
    assert notes[0].startswith("noise law: measured on ") and notes[1].startswith("amplitude unit: V^2 (not given")
    assert len(notes) == 3 and notes[2].startswith("frequency offsets: ")
    assert correction_notes(raw)[1:] == correction_notes(correction)[1:2], "nothing fused, no offsets measured"


@pytest.mark.unit
@pytest.mark.parametrize("whole_cycles", [False, True])
def test_fused_depth__removes_the_window_s_leakage_only_from_a_sensor_that_has_it(pixelwise_model, whole_cycles):
    config = Config(simulator=SimulatorConfig(whole_cycles=whole_cycles, noise_scale=0.2))
    scan = render(flat_wall(20.0, 1.0, 0.7, height=48, width=64), config, np.random.default_rng(3))
    options = CorrectionOptions(amplitude_scale=1.0, noise_scale=0.2)
    correction = correct_scan(scan, load_model(pixelwise_model), options)
    assert correction.window_leakage_removed is not whole_cycles
    said = "removed first" if not whole_cycles else "left in"
    assert f"the integration window's leakage {said}" in correction_notes(correction)[-1], correction_notes(correction)
    fused = correction.estimate == Estimate.FUSED
    assert fused.mean() > 0.9
    # At 1 m the leakage leaves the highest frequency 0.18 mm short, which no relative offset removes; a fifth of
    # the noise leaves the fused depths' mean within 0.03 mm of the truth.
    bias_m = float(np.mean(correction.depth[fused] - scan.reference_depth[fused]))
    assert abs(bias_m) < 3e-5, bias_m
    assert np.abs(np.asarray(correction.frequency_offsets_m)).max() < 1e-4, "nothing left to remove but noise"


@pytest.mark.unit
@pytest.mark.parametrize("window_leakage_removed", [None, True])
def test_fused_depth__a_profile_s_offsets_say_whether_the_leakage_goes_first(pixelwise_model, window_leakage_removed):
    scan = render(flat_wall(20.0, 1.0, 0.7, height=48, width=64), Config(), np.random.default_rng(3))
    offsets = (-2e-5, 1e-5, 0.0, 0.0)
    options = CorrectionOptions(frequency_offsets_m=offsets, window_leakage_removed=window_leakage_removed)
    correction = correct_scan(scan, load_model(pixelwise_model), options)
    assert correction.window_leakage_removed is bool(window_leakage_removed)
    assert correction.frequency_offsets_m == offsets
    fused = correction.estimate == Estimate.FUSED
    expected = inverse_variance_mean(scan, offsets, window=bool(window_leakage_removed))
    np.testing.assert_allclose(correction.depth[fused], expected[fused], rtol=0, atol=2e-6)


@pytest.mark.unit
def test_correct_scan__says_how_many_corrected_pixels_lie_beyond_the_model_s_prior(tmp_path):
    from tests.model_factory import tiny_model

    model = load_model(tiny_model(tmp_path / "model", geometric=True))
    reach = model.card.dataset.prior.multipath_reach()
    assert reach is not None and reach[1] == pytest.approx(model.card.dataset.prior.model_extra["d_ab_m"][1])
    sharp = correct_scan(render(corner(60.0, 2.0, 0.8, height=40, width=96), Config(), np.random.default_rng(2)),
                         model, CorrectionOptions(gate="all", footprint_area_m2=0.041))
    said = [note for note in correction_notes(sharp) if "beyond what the model was trained on" in note]
    assert len(said) == 1, correction_notes(sharp)
    beyond = int(said[0].split(" corrected pixels")[0].replace(",", ""))
    assert 0 < beyond == sharp.counts()["beyond_prior"], "each has its own flag"
    wall = correct_scan(render(flat_wall(20.0, height=40, width=64), Config(), np.random.default_rng(2)), model,
                        CorrectionOptions(gate="all", footprint_area_m2=0.041))
    assert not any("beyond what the model" in note for note in correction_notes(wall)), \
        "a wall has no multipath to extrapolate"


@pytest.mark.unit
def test_geometry_gate__corner_is_corrected_near_its_edge_only(pixelwise_model):
    scan = render(corner(90.0, 2.0, 0.8, height=40, width=96), Config(), np.random.default_rng(2))
    correction = correct_scan(scan, load_model(pixelwise_model), CorrectionOptions(baseline="raw"))
    row = correction.flags[20]
    assert (row[40:56] == Flag.CORRECTED).all(), "the edge is at the centre column"
    assert correction.counts()["corrected"] > 0.2 * row.size * 40
    far = correction.flags == Flag.NO_MULTIPATH
    np.testing.assert_array_equal(correction.depth[far], scan.depth[-1][far])
    bias = correction.multipath_bias_m[20]
    assert bias[42:55].max() > bias[64] > bias[80] > bias[92] >= 0, "largest next to the edge, falling away"


@pytest.mark.unit
def test_geometry_gate__scan_without_geometry_falls_back_and_says_so(pixelwise_model, tmp_path):
    scan = replace(two_path_scan("nogeo"), azimuth_rad=None, elevation_rad=None)
    correction = correct_scan(scan, load_model(pixelwise_model), CorrectionOptions())
    assert correction_notes(correction)[2] == NO_GEOMETRY_NOTE and correction.frequency_offsets_m is None
    assert "no scene geometry" in correction_notes(correction)[3]
    assert (correction.flags == Flag.CORRECTED).all() and correction.multipath_bias_m is None
    write_scan(scan, tmp_path / "nogeo.scan.zarr")
    outcome = process_scan(tmp_path / "nogeo.scan.zarr", pixelwise_model, tmp_path / "out", CorrectionOptions(),
                           outputs=LIGHT)
    assert outcome.status == "corrected" and NO_GEOMETRY_NOTE in outcome.notes
    assert NO_GEOMETRY_NOTE in (tmp_path / "out" / "nogeo" / "report.md").read_text()
    stored = zarr.open_group(str(tmp_path / "out" / "nogeo" / "corrected.zarr"), mode="r")
    assert "multipath_bias_m" not in stored and stored.attrs["flag_codes"]["no_multipath"] == 7


@pytest.mark.unit
def test_flag__existing_codes_are_stable():
    assert [int(f) for f in Flag] == list(range(14))
    assert Flag.NO_MULTIPATH == 7 and Flag.OUT_OF_RANGE == 6 and Flag.CORRECTED == 0 and Flag.UNCALIBRATED == 8
    assert Flag.AMBIGUOUS == 9 and Flag.BEYOND_AMBIGUITY == 10 and Flag.MIXED == 11 and Flag.TWO_RETURNS == 12
    assert Flag.BEYOND_PRIOR == 13


@pytest.mark.unit
def test_scan_status__degraded_then_unchanged_then_corrected():
    from mpi_lidar.correction.outcome import scan_status

    assert scan_status({"corrected": 5, "no_multipath": 5}, 0.5) == ScanStatus.CORRECTED
    assert scan_status({"corrected": 0, "no_multipath": 9, "out_of_range": 1}, 0.5) == ScanStatus.UNCHANGED
    assert scan_status({"corrected": 4, "saturated": 6}, 0.5) == ScanStatus.DEGRADED
    assert scan_status({"corrected": 0, "no_return": 6, "no_multipath": 4}, 0.5) == ScanStatus.DEGRADED
    assert scan_status({"corrected": 5, "inconsistent": 5}, 0.5) == ScanStatus.CORRECTED, "half is not above half"
    assert scan_status({"corrected": 4, "not_finite": 6}, 1.0) == ScanStatus.CORRECTED


@pytest.mark.unit
def test_correction_options__max_invalid_share_is_bounded_and_not_hashed():
    # the hash of the defaults before max_invalid_share, the self-calibrating footprint, the near range and
    # unwrapping existed: unwrapping changes the pixels of wrapped scans, so outputs written then are corrected
    # again (at 6 m every pixel was lost before)
    from mpi_lidar.physics.coupling import DEFAULT_FOOTPRINT_AREA_M2

    old_defaults = CorrectionOptions(footprint_area_m2=DEFAULT_FOOTPRINT_AREA_M2, near_range_fraction=0.0)
    assert old_defaults.sha256() != "60f34a4236aaaebe7317d65a6b26b44fb18bdd6d4b7e20a9cb91fc30bd1028ed"
    # correcting depths below the prior changes pixels: not the same identity
    assert CorrectionOptions(footprint_area_m2=DEFAULT_FOOTPRINT_AREA_M2).sha256() != old_defaults.sha256()
    assert CorrectionOptions(max_invalid_share=0.9).sha256() == CorrectionOptions().sha256()
    assert CorrectionOptions().sha256() != old_defaults.sha256()  # auto changes pixels: not the same identity
    assert CorrectionOptions.from_cli(max_invalid_share=0.25).max_invalid_share == 0.25
    for bad in (-0.1, 1.5, float("nan")):
        with pytest.raises(MpiLidarError, match="max_invalid_share"):
            CorrectionOptions.from_cli(max_invalid_share=bad)


@pytest.mark.unit
def test_correct_cli__gate_threshold_and_footprint_reach_the_gate(pixelwise_model, tmp_path):
    scan = render(corner(90.0, 2.0, 0.8, height=24, width=48), Config(), np.random.default_rng(3))
    write_scan(scan, tmp_path / "corner.scan.zarr")

    def flags_with(*options: str) -> np.ndarray:
        out = tmp_path / f"out{len(list(tmp_path.iterdir()))}"
        arguments = ["correct", str(tmp_path / "corner.scan.zarr"), "--model", str(pixelwise_model), "--out", str(out),
                     "--workers", "0", *options]
        assert CliRunner().invoke(cli, arguments).exit_code == 0
        return zarr.open_group(str(out / "corner" / "corrected.zarr"), mode="r")["flags"][:]  # the store name

    footprint = ("--footprint-area-m2", "0.041")  # this small scan is too small to measure its own
    default = flags_with(*footprint)
    every = flags_with("--min-bias-mm", "0", *footprint)
    blind = flags_with("--footprint-area-m2", "1e-12")
    assert 0 < (default == Flag.CORRECTED).sum() < (every == Flag.CORRECTED).sum()
    assert not (every == Flag.NO_MULTIPATH).any(), "a zero threshold lets every valid pixel through"
    assert not (blind == Flag.CORRECTED).any(), "a vanishing footprint leaves no multipath potential"


@pytest.mark.unit
def test_correction_options__amplitude_scale_auto_or_a_positive_number():
    assert CorrectionOptions.from_cli(amplitude_scale="auto").amplitude_scale == "auto"
    assert CorrectionOptions.from_cli(amplitude_scale="4000").amplitude_scale == 4000.0
    assert CorrectionOptions().amplitude_scale == "auto", "each scan reads its own unit by default"
    assert CorrectionOptions(amplitude_scale=4000.0).sha256() != CorrectionOptions().sha256()
    assert CorrectionOptions(amplitude_scale=1.0).sha256() != CorrectionOptions().sha256()
    for bad in ("-1", "0", "nan", "many"):
        with pytest.raises(MpiLidarError, match=r"amplitude_scale must be 'auto' or a number of units per V\^2"):
            CorrectionOptions.from_cli(amplitude_scale=bad)
