"""The footprint estimate (mpi_lidar.correction.footprint): against the renderer's true footprint, and what
correction and calibration do with it."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
import zarr

from mpi_lidar.calibration.profile import read_profile
from mpi_lidar.config import Config
from mpi_lidar.correction import CorrectionOptions, Flag, correct_scan
from mpi_lidar.correction.corrected_store import footprint_record
from mpi_lidar.correction.footprint import (
    FootprintEstimate,
    block_albedo,
    estimate_footprint,
    pool_estimates,
    surface_labels,
)
from mpi_lidar.correction.footprint._albedo import light_free_albedo, surface_albedo
from mpi_lidar.correction.footprint._coupling import PlaneCoupling
from mpi_lidar.correction.footprint._estimate import evenly_chosen
from mpi_lidar.errors import MpiLidarError
from mpi_lidar.learning.model import load_model
from mpi_lidar.reporting.correction_notes import correction_notes
from mpi_lidar.scans.geometry import facing_blocks
from mpi_lidar.simulation.scenes import DEFAULT_FOOTPRINT_RADIUS_M, corner, flat_wall, render, room_corner
from mpi_lidar.workflows.calibrate import calibrate_scans, scan_footprint
from tests.cli_runner import assert_one_error_line, call_main
from tests.render_cache import transport_shared_as

_RENDERS: dict[tuple, object] = {}


def rendered(scene, footprint_m2: float, seed: int = 1, noise: float = 1.0, patch_spacing_m: float | None = None):
    """A render whose true receiver footprint is ``footprint_m2`` (A_fp = gain pi r^2).

    Rendered once per session for the same arguments and shared by the tests that ask for it: its arrays are
    read-only, so no test can change what another sees. Without multipath (a footprint of 0) the partner
    patches add exactly nothing to any pixel, so they are taken coarse: the same scan, bit for bit, sooner.
    Renders of one scene that differ in the seed or the noise alone share its light transport, which draws
    nothing and reads neither (the sensor model draws the noise): the same scans, bit for bit, without a
    second transport (5 s of a room corner's).
    """
    if footprint_m2 == 0 and patch_spacing_m is None:
        patch_spacing_m = 1.0
    key = (scene.name, scene.surfaces, scene.azimuth_rad.tobytes(), scene.elevation_rad.tobytes(), footprint_m2,
           seed, noise, patch_spacing_m)
    if key not in _RENDERS:
        config = Config().replace(simulator={"noise_scale": noise})
        gain, rng = footprint_m2 / (np.pi * DEFAULT_FOOTPRINT_RADIUS_M**2), np.random.default_rng(seed)
        with transport_shared_as(key[:5] + key[7:]):
            scan = render(scene, config, rng, coupling_gain=gain, patch_spacing_m=patch_spacing_m)
        for value in vars(scan).values():
            if isinstance(value, np.ndarray):
                value.flags.writeable = False
        _RENDERS[key] = scan
    return _RENDERS[key]


def estimate(scan, reference: bool = False) -> FootprintEstimate:
    valid = np.isfinite(scan.depth[-1]).ravel()
    blocks = facing_blocks(np.where(valid.reshape(scan.shape), scan.depth[-1], np.nan), scan.rays())
    return estimate_footprint(scan, blocks, valid, Config().sensor, reference=reference)


@pytest.mark.integration
@pytest.mark.slow
@pytest.mark.parametrize("true_m2", [0.004, 0.041])
def test_estimate__against_a_reference_depth_finds_the_renders_footprint(true_m2):
    # The renderer's own footprint is the independent truth; against the exact reference depth only the
    # scan's geometry (3 cm planes, the field of view) separates the model from the render.
    found = estimate(rendered(corner(90.0, 2.0, 0.8), true_m2), reference=True)
    assert found.significant and found.method == "reference"
    assert found.area_m2 == pytest.approx(true_m2, rel=0.25)


@pytest.mark.integration
@pytest.mark.slow
def test_estimate__from_the_scans_own_surfaces_at_a_small_footprint():
    found = estimate(rendered(corner(90.0, 2.0, 0.8), 0.002))
    assert found.significant and found.surfaces >= 2 and found.pixels > 5000
    assert 1 / 1.5 <= found.area_m2 / 0.002 <= 1.5


@pytest.mark.integration
@pytest.mark.slow
def test_estimate__three_surfaces_of_a_room_corner_measure_the_footprint():
    # Two walls and the floor face each other along three edges: every one is a partner of the other two.
    # The walls' patches 4 cm apart, as the renderer takes them for the scenes of a room's size (multi_object):
    # at 2 cm this one render took 20 s.
    found = estimate(rendered(room_corner(), 0.041, patch_spacing_m=0.04))
    assert found.significant and found.surfaces >= 3
    assert 1 / 1.5 <= found.area_m2 / 0.041 <= 1.5


@pytest.mark.unit
def test_estimate__a_flat_wall_measures_nothing_usable():
    found = estimate(rendered(flat_wall(0.0), 0.041))
    assert not found.significant


@pytest.mark.integration
@pytest.mark.slow
def test_estimate__strong_multipath_on_a_near_corner_is_read_within_1_5x():
    # At 0.1 m^2 the multipath bends the boards far from the edge, and the planes the depth is measured
    # against take up part of the bias: the depth alone reads about half the truth here. The amplitude's
    # gain, measured against each board's own albedo, does not.
    found = estimate(rendered(corner(90.0, 1.4, 0.9), 0.1, seed=0))
    assert found.significant
    assert 1 / 1.5 <= found.area_m2 / 0.1 <= 1.5


def board_albedos(scene, true_m2: float) -> tuple[list[float], list[float], list[float]]:
    """Per board of a rendered corner: its light-free albedo at the true footprint, and the albedo of its
    measured amplitude over its far blocks chosen by the model's coupling and by the visible block pairs'."""
    scan = rendered(scene, true_m2, seed=0)
    depth = scan.depth[-1]
    blocks = facing_blocks(np.where(np.isfinite(depth), depth, np.nan), scan.rays())
    surfaces = surface_labels(blocks)
    components = surfaces.components
    plane = PlaneCoupling(scan, blocks, surfaces, Config().sensor)
    measured = block_albedo(scan, blocks, Config().sensor)
    pair_kappa = np.bincount(blocks.index[blocks.pairs.a], blocks.pairs.kappa(1.0), minlength=blocks.usable.size)
    found = (light_free_albedo(plane, measured, components, true_m2),
             surface_albedo(measured, components, plane.coupling_at_blocks),
             surface_albedo(measured, components, pair_kappa))
    boards = [np.flatnonzero(components == c)[0] for c in np.unique(components[components >= 0])
              if (components == c).sum() > 20]
    return tuple([float(albedo[b]) for b in boards] for albedo in found)


@pytest.mark.integration
def test_light_free_albedo__strong_multipath_is_taken_off_the_boards_amplitude():
    # At 0.1 m^2 the partners add a tenth to the light of a near corner's boards even far from the edge; an
    # albedo that keeps it overstates the partners' product and reads the footprint low.
    light_free, measured, _ = board_albedos(corner(90.0, 1.4, 0.9), 0.1)
    assert len(light_free) == 2
    for free, raw in zip(light_free, measured, strict=True):
        assert raw > 1.07 * 0.9
        assert abs(free - 0.9) < 0.6 * (raw - 0.9)


@pytest.mark.integration
@pytest.mark.slow
def test_light_free_albedo__far_blocks_are_those_the_model_couples_least():
    # Along a horizontal edge the row of blocks next to it has no facing block pairs (too close), yet the most
    # coupling and bent normals: taken as far blocks they read one board 5 % dark and, less the gain the
    # model gives them, 16 % dark at a footprint that adds almost no light.
    light_free, measured, by_pairs = board_albedos(
        corner(100.0, 1.45, 0.65, board_m=0.45, half_height_m=0.5, roll_deg=90), 0.004)
    assert len(light_free) == 2
    assert min(by_pairs) < 0.95 * 0.65
    assert all(abs(albedo / 0.65 - 1) < 0.03 for albedo in light_free + measured)


@pytest.mark.unit
@pytest.mark.parametrize(("shape", "share", "count"), [((50, 70), 0.3, 100), ((3, 5), 0.5, 2), ((400, 300), 0.01, 1000),
                                                  ((40, 30), 0.9, 10_000), ((10, 10), 0.0, 5), ((100, 100), 1.0, 37)])
def test_fit_pixels__row_by_row_stride_picks_what_the_flat_stride_picks(shape, share, count):
    mask = np.random.default_rng(1).random(shape) < share
    every = np.flatnonzero(mask)
    expected = every[np.linspace(0, every.size - 1, count).astype(np.intp)] if every.size > count else every
    np.testing.assert_array_equal(evenly_chosen(mask, count), expected)


@pytest.mark.unit
def test_pool__is_the_inverse_variance_mean():
    a, b = FootprintEstimate(0.01, 0.001, 100, 2), FootprintEstimate(0.02, 0.002, 300, 2)
    pooled = pool_estimates([a, b, FootprintEstimate(float("nan"), float("inf"), 0, 0)])
    weights = np.array([1e6, 0.25e6])
    assert pooled.area_m2 == pytest.approx((weights * [0.01, 0.02]).sum() / weights.sum())
    assert pooled.sigma_m2 == pytest.approx(weights.sum() ** -0.5)
    assert pooled.scans == 3 and pooled.pixels == 400


@pytest.mark.unit
def test_correct__auto_on_a_flat_wall_keeps_every_raw_depth(tiny_geometric_model):
    scan = rendered(flat_wall(20.0), 0.041)
    correction = correct_scan(scan, tiny_geometric_model, CorrectionOptions(footprint_area_m2="auto",
                                                                            baseline="raw"))
    valid = correction.flags != Flag.NOT_FINITE
    assert np.array_equal(correction.depth[valid], scan.depth[-1][valid])
    assert correction.counts()["corrected"] == 0


@pytest.mark.integration
@pytest.mark.slow
def test_correct__an_estimate_that_is_not_significant_leaves_its_pixels_as_measured(tiny_geometric_model):
    # A dark corner (albedo 0.1): the multipath is too weak to measure the footprint on. (At three times the noise
    # its 3 cm block planes are lost in the noise: no pair faces, nothing could hold multipath.)
    scan = rendered(corner(90.0, 2.0, 0.1), 0.041)
    correction = correct_scan(scan, tiny_geometric_model, CorrectionOptions(footprint_area_m2="auto",
                                                                           min_multipath_bias_m=1e-4,
                                                                           baseline="raw"))
    assert correction.calibration is not None and not correction.calibration.significant
    assert correction.counts()["corrected"] == 0 and correction.counts()["uncalibrated"] > 0
    left = np.isin(correction.flags, [Flag.UNCALIBRATED, Flag.NO_MULTIPATH])
    assert np.array_equal(correction.depth[left], scan.depth[-1][left])
    assert any("not significant" in note and "uncalibrated" in note for note in correction_notes(correction))


@pytest.mark.integration
def test_correct__a_significant_estimate_is_used_and_reported(tiny_geometric_model):
    scan = rendered(corner(90.0, 2.0, 0.8), 0.02)
    correction = correct_scan(scan, tiny_geometric_model, CorrectionOptions(footprint_area_m2="auto"))
    assert correction.calibration.significant and correction.counts()["corrected"] > 0
    given = correct_scan(scan, tiny_geometric_model,
                         CorrectionOptions(footprint_area_m2=correction.calibration.area_m2))
    assert np.array_equal(given.depth, correction.depth, equal_nan=True)  # auto is the number it found
    record = footprint_record(correction)
    assert record["area_m2"] == correction.calibration.area_m2 and record["significant"]
    low, high = sorted([record["depth_m2"], record["amplitude_m2"]])
    assert 0 < low <= record["area_m2"] <= high  # the joined estimate lies between its two measurements


@pytest.mark.integration
@pytest.mark.parametrize("albedo", [0.8, 0.3])
def test_correct__a_scan_in_another_unit_measures_the_footprint_for_white_surfaces(tiny_geometric_model, albedo):
    # Amplitudes in counts (4000 per V^2) read as V^2 make every surface far brighter than white: the unit is
    # contradicted and the model is not applied. The footprint, measured with white surfaces, is the true one
    # times the albedos the light returns from, rho_A rho_B (F5), and the uncertainty of the depths left alone
    # covers the multipath the correction in V^2 corrects (before: an albedo clipped at 1.5 read the footprint
    # 2-3x too small, and 49 % of the bright corner's multipath pixels were covered).
    true_m2 = 0.04
    scan = rendered(corner(90.0, 2.0, albedo), true_m2, seed=0)
    in_v2 = correct_scan(scan, tiny_geometric_model)
    in_counts = correct_scan(replace(scan, amplitude=scan.amplitude * np.float32(4000.0)), tiny_geometric_model)
    assert not in_counts.reading.unit_trusted and in_counts.counts()["corrected"] == 0
    found = in_counts.calibration
    assert found.significant and found.white_surfaces and not in_v2.calibration.white_surfaces
    assert 1 / 1.3 <= found.area_m2 / (true_m2 * albedo**2) <= 1.3
    multipath = np.isin(in_v2.flags, [Flag.CORRECTED, Flag.BEYOND_PRIOR])
    error = np.abs(in_counts.depth - scan.reference_depth)[multipath]
    assert multipath.sum() > 1000 and np.median(error) > 1.5e-3  # the multipath is there, left alone
    assert 0.6 <= (error <= in_counts.uncertainty_m[multipath]).mean() <= 0.85
    assert any("taken as white" in note for note in correction_notes(in_counts))
    assert in_counts.calibration.to_dict()["albedos"] == "white"
    # Nothing of it rests on the unit: a unit far smaller than V^2 (contradicted too) measures the same footprint.
    in_smaller = correct_scan(replace(scan, amplitude=scan.amplitude / np.float32(4000.0)), tiny_geometric_model)
    assert not in_smaller.reading.unit_trusted
    assert in_smaller.calibration.area_m2 == pytest.approx(found.area_m2, rel=0.01)


@pytest.mark.unit
def test_options__footprint_accepts_auto_or_a_positive_number():
    assert CorrectionOptions.from_cli(footprint_area_m2="AUTO").self_calibrating
    assert CorrectionOptions.from_cli(footprint_area_m2="0.02").footprint_area_m2 == 0.02
    assert CorrectionOptions().self_calibrating
    for bad in ("wide", "-1", "0"):
        with pytest.raises(MpiLidarError, match="footprint_area_m2"):
            CorrectionOptions.from_cli(footprint_area_m2=bad)


@pytest.mark.unit
@pytest.mark.parametrize("text, fragment", [("footprint_area_m2 = \n", "not valid TOML"),
                                            ("footprint_area_m2 = -1.0\n", "invalid"),
                                            ("footprint = 0.02\n", "invalid")])
def test_profile__bad_files_are_one_line_errors(tmp_path, monkeypatch, capsys, text, fragment):
    bad = tmp_path / "bad.toml"
    bad.write_text(text)
    scan = tmp_path / "none.scan.zarr"
    code, _, stderr = call_main(monkeypatch, capsys, "correct", str(scan), "--model", str(tmp_path), "--out",
                                str(tmp_path / "out"), "--sensor", str(bad))
    assert code == 2 and fragment in stderr and str(bad) in stderr
    assert_one_error_line(stderr)
    assert not (tmp_path / "out").exists()


@pytest.mark.integration
@pytest.mark.slow
def test_calibrate__pools_scans_writes_a_profile_that_correct_records(tmp_path, tiny_geometric_model_dir,
                                                                      monkeypatch, capsys):
    from mpi_lidar.scans.store import write_scan

    for seed in (1, 2):
        write_scan(rendered(corner(90.0, 2.0, 0.8), 0.02, seed=seed), tmp_path / "scans" / f"c{seed}.scan.zarr")
    profile, results = calibrate_scans([str(tmp_path / "scans")], tmp_path / "sensor.toml")
    assert len(results) == 2 and all(r.estimate.method == "reference" for r in results)
    assert profile.footprint_area_m2 == pytest.approx(0.02, rel=0.3)
    assert read_profile(tmp_path / "sensor.toml").footprint_area_m2 == profile.footprint_area_m2
    code, _, stderr = call_main(monkeypatch, capsys, "correct", str(tmp_path / "scans" / "c1.scan.zarr"), "--model",
                                str(tiny_geometric_model_dir), "--out", str(tmp_path / "out"), "--sensor",
                                str(tmp_path / "sensor.toml"), "--workers", "0")
    assert code == 0, stderr
    attrs = zarr.open_group(str(tmp_path / "out" / "c1" / "corrected.zarr"), mode="r").attrs
    assert attrs["options"]["footprint_area_m2"] == profile.footprint_area_m2
    assert attrs["options"]["sensor_profile_sha256"] == profile.record()["sha256"]


@pytest.mark.unit
def test_calibrate__refuses_scans_without_facing_surfaces(tmp_path, monkeypatch, capsys):
    from mpi_lidar.scans.store import write_scan

    write_scan(rendered(flat_wall(0.0), 0.041), tmp_path / "wall.scan.zarr")
    code, _, stderr = call_main(monkeypatch, capsys, "calibrate", str(tmp_path / "wall.scan.zarr"), "--out",
                                str(tmp_path / "sensor.toml"), "--no-reference")
    assert code == 2 and "the scan gives no significant footprint" in stderr, "one scan, in the singular"
    assert_one_error_line(stderr)
    assert not (tmp_path / "sensor.toml").exists()


@pytest.mark.integration
def test_scan_footprint__a_scan_without_geometry_measures_nothing():
    from dataclasses import replace

    scan = replace(rendered(corner(90.0, 2.0, 0.8), 0.02), azimuth_rad=None, elevation_rad=None)
    assert not np.isfinite(scan_footprint(scan, CorrectionOptions(), Config().sensor).area_m2)


@pytest.mark.unit
def test_calibrate__scans_in_counts_give_their_unit_and_correct_as_in_v2(tmp_path, tiny_geometric_model_dir,
                                                                         monkeypatch, capsys):
    from dataclasses import replace

    from mpi_lidar.scans.store import write_scan

    for seed in (1, 2):  # walls and a floor: flat regions away from the edges measure the unit
        scan = rendered(room_corner(height=64, width=86), 0.02, seed=seed)
        write_scan(scan, tmp_path / "v2" / f"c{seed}.scan.zarr")
        write_scan(replace(scan, amplitude=(scan.amplitude * 4000).astype(np.float32)),
                   tmp_path / "counts" / f"c{seed}.scan.zarr")
    profile, results = calibrate_scans([str(tmp_path / "counts")], tmp_path / "sensor.toml")
    assert all(r.scale is not None and r.scale.significant for r in results)
    assert profile.amplitude_scale == pytest.approx(4000, rel=0.1)
    assert profile.frequencies_hz == Config().frequencies_hz
    assert profile.range_m is not None and 0.5 < profile.range_m[0] < profile.range_m[1] < 4.0
    assert read_profile(tmp_path / "sensor.toml") == profile
    outputs = {}
    for unit, extra in (("v2", []), ("counts", ["--amplitude-scale", str(profile.amplitude_scale)])):
        code, _, stderr = call_main(monkeypatch, capsys, "correct", str(tmp_path / unit / "c1.scan.zarr"), "--model",
                                    str(tiny_geometric_model_dir), "--out", str(tmp_path / f"out-{unit}"),
                                    "--footprint-area-m2", "0.02", "--workers", "0", *extra)
        assert code == 0, stderr
        outputs[unit] = zarr.open_group(str(tmp_path / f"out-{unit}" / "c1" / "corrected.zarr"),
                                        mode="r")["corrected_depth"][:]
    # the unit is known to a few %: the amplitudes it gives differ from V^2 by that, and the depths by far less
    # (a pixel near a tree's split or the gate's threshold may go the other way)
    difference = np.abs(outputs["counts"] - outputs["v2"])
    assert np.nanmean(difference) < 0.05e-3 and np.nanmean(difference > 1e-4) < 0.05


@pytest.mark.unit
def test_correct_scan__a_unit_is_never_read_from_the_scatter_and_never_wrongly_applied(tiny_geometric_model_dir):
    from dataclasses import replace

    from mpi_lidar.correction import correct_scan
    from mpi_lidar.correction.options import Estimate, UnservedReason

    model = load_model(tiny_geometric_model_dir)
    corner_scan = rendered(corner(90.0, 2.0, 0.8), 0.02)
    scaled = {unit: replace(corner_scan, amplitude=(corner_scan.amplitude * unit).astype(np.float32))
              for unit in (1.0, 4000.0, 0.01)}
    # Without the unit: V^2 is corrected; counts and x 0.01 contradict V^2 (surfaces far too bright, far too dark)
    # and are not corrected, their fused depths the same as in V^2.
    runs = {unit: correct_scan(scan, model) for unit, scan in scaled.items()}
    assert runs[1.0].unserved is None and runs[1.0].counts()["corrected"] > 0
    for unit in (4000.0, 0.01):
        assert runs[unit].unserved is not None and runs[unit].unserved.reason == UnservedReason.AMPLITUDE_UNITS
        assert runs[unit].counts()["corrected"] == 0
        fused = (runs[unit].estimate == Estimate.FUSED) & (runs[1.0].estimate == Estimate.FUSED)
        assert fused.sum() > 1000
        np.testing.assert_allclose(runs[unit].depth[fused], runs[1.0].depth[fused], rtol=0, atol=0.05e-3)
    # With the unit given: the same correction as in V^2.
    for unit in (4000.0, 0.01):
        given = correct_scan(scaled[unit], model, CorrectionOptions(amplitude_scale=unit))
        assert given.unserved is None
        np.testing.assert_array_equal(given.flags, runs[1.0].flags)
        np.testing.assert_allclose(given.depth, runs[1.0].depth, rtol=0, atol=0.05e-3)
