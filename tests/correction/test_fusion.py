"""The fused depth: inverse-variance weights from the noise model, offsets removed, consistency, uncertainty."""

from __future__ import annotations

import numpy as np
import pytest

from mpi_lidar.config import Config, SensorConfig
from mpi_lidar.correction import CorrectionOptions, correct_scan
from mpi_lidar.correction.options import Estimate, Flag
from mpi_lidar.learning.model import load_model
from mpi_lidar.physics.noise import FUSION_P_VALUE, depth_noise_m, fused_depths
from mpi_lidar.simulation.scenes import flat_wall, render
from tests.model_factory import tiny_model

FREQS = Config().frequencies_hz


def _rows(depth: np.ndarray, amplitude: float) -> np.ndarray:
    """Raw rows (n, 2F) of the given depths (n, F) [m] at one amplitude [V^2] at every frequency."""
    return np.hstack([depth, np.full_like(depth, amplitude)])


@pytest.mark.unit
def test_fused_depths__equal_depths_give_that_depth_and_the_cramer_rao_sd():
    rows = _rows(np.full((3, 4), 2.5), 0.01)
    fused = fused_depths(rows, FREQS, SensorConfig())
    sd = depth_noise_m(SensorConfig(), FREQS, np.full((1, 4), 0.01))[0]
    np.testing.assert_allclose(fused.depth_m, 2.5, rtol=0, atol=1e-6)
    np.testing.assert_allclose(fused.sigma_m, np.sum(sd**-2.0) ** -0.5, rtol=1e-6)
    np.testing.assert_allclose(fused.top_sigma_m, sd[-1], rtol=1e-6)
    assert fused.consistent.all() and np.all(fused.birge_ratio < 1e-6)
    assert 0.6 < fused.sigma_m[0] / sd[-1] < 0.75, "four frequencies: about 0.68 of the highest one's sd"


@pytest.mark.unit
def test_fused_depths__weights_are_inverse_variances_and_offsets_are_removed():
    sensor = SensorConfig()
    sd = depth_noise_m(sensor, FREQS, np.full((1, 4), 0.01))[0]
    depth = np.array([[2.0, 2.0, 2.0, 2.0 + 1e-3]])
    fused = fused_depths(_rows(depth, 0.01), FREQS, sensor)
    weight = sd**-2.0
    assert fused.depth_m[0] == pytest.approx(2.0 + 1e-3 * weight[-1] / weight.sum(), abs=1e-7)
    offsets = (1e-3, 0.0, -1e-3, 0.0)
    shifted = fused_depths(_rows(np.array([[2.0 + 1e-3, 2.0, 2.0 - 1e-3, 2.0]]), 0.01), FREQS, sensor,
                           offsets_m=offsets)
    assert shifted.depth_m[0] == pytest.approx(2.0, abs=1e-7)
    scaled = fused_depths(_rows(depth, 0.01), FREQS, sensor, noise_scale=2.0)
    assert scaled.depth_m[0] == fused.depth_m[0] and scaled.sigma_m[0] == pytest.approx(2 * fused.sigma_m[0])


@pytest.mark.unit
def test_fused_depths__frequencies_that_disagree_beyond_noise_are_not_consistent():
    rng = np.random.default_rng(0)
    sd = depth_noise_m(SensorConfig(), FREQS, np.full((1, 4), 0.01))[0]
    noisy = 2.0 + rng.standard_normal((200_000, 4)) * sd
    fused = fused_depths(_rows(noisy, 0.01), FREQS, SensorConfig())
    assert (~fused.consistent).mean() == pytest.approx(FUSION_P_VALUE, rel=0.3), "chi-square at its p-value"
    apart = np.array([[2.0, 2.0, 2.0, 2.0 + 20 * sd[-1]]])
    assert not fused_depths(_rows(apart, 0.01), FREQS, SensorConfig()).consistent[0]


@pytest.fixture(scope="module")
def tiny_geometric_model(tmp_path_factory):
    return load_model(tiny_model(tmp_path_factory.mktemp("fusion") / "model", geometric=True))


@pytest.mark.integration
def test_correct_scan__a_wall_is_fused_and_its_uncertainty_covers_about_68_percent(tiny_geometric_model):
    scan = render(flat_wall(20.0, 2.0, 0.7, height=48, width=64), Config(), np.random.default_rng(3),
                  patch_spacing_m=1.0)
    correction = correct_scan(scan, tiny_geometric_model)
    valid = ~np.isin(correction.flags, [Flag.NOT_FINITE, Flag.NO_RETURN, Flag.SATURATED, Flag.INCONSISTENT])
    assert (correction.estimate[valid] == Estimate.FUSED).mean() > 0.99
    assert (correction.estimate[~valid] == Estimate.NONE).all()
    error = np.abs(correction.depth - scan.reference_depth)[valid]
    raw_error = np.abs(scan.depth[-1] - scan.reference_depth)[valid]
    assert error.mean() < 0.75 * raw_error.mean()
    covered = (error <= correction.uncertainty_m[valid]).mean()
    assert 0.63 < covered < 0.73, f"a calibrated Gaussian sigma covers 68 %, got {100 * covered:.1f} %"
    raw = correct_scan(scan, tiny_geometric_model, CorrectionOptions(baseline="raw"))
    np.testing.assert_array_equal(raw.depth[valid], scan.depth[-1][valid])
    assert (raw.estimate[valid] == Estimate.MEASURED).all()
    raw_covered = (raw_error <= raw.uncertainty_m[valid]).mean()
    assert 0.63 < raw_covered < 0.73, "the measured depth's sd covers its error as often"


@pytest.mark.integration
def test_noise_limit_benchmark__quick_rows_fuse_the_wall_and_leave_the_corner_edge(tmp_path):
    from benchmarks.noise_limit import HEADER, format_row, run

    rows = dict(run(str(tiny_model(tmp_path / "model", geometric=True)), quick=True))
    wall, corner = rows["wall at 2 m"], rows["corner at 2 m, 0.073 m^2"]
    assert wall["share_fused"] > 0.99 and wall["fused_baseline"] < 0.75 * wall["raw_baseline"]
    assert wall["fused_over_crb"] == pytest.approx(1.0, abs=0.15), "fused pixels at their Cramer-Rao bound"
    assert 0.6 < wall["covered_all"] < 0.76
    assert corner["fused_baseline"] <= corner["raw_baseline"] + 1e-6, "fusing the rest never costs a scan"
    assert corner["edge_fused_baseline"] == pytest.approx(corner["edge_raw_baseline"], abs=0.05)
    columns = {len(line.strip("|").split("|")) for line in [*HEADER.splitlines(), format_row("x", wall)]}
    assert columns == {10}


@pytest.mark.integration
def test_correct_scan__a_wrapped_scan_corrects_as_the_same_scan_unwrapped(tiny_geometric_model):
    from dataclasses import replace

    from mpi_lidar.physics.demod import unambiguous_range

    scan = render(flat_wall(20.0, 6.0, 0.7, height=24, width=32), Config(), np.random.default_rng(9),
                  patch_spacing_m=1.0)
    ambiguity = unambiguous_range(np.asarray(scan.frequencies_hz), 3e8)[:, None, None]
    counts = np.rint((scan.reference_depth[None] - scan.depth) / ambiguity)
    assert counts[-1].min() >= 1, "past 4.8 m the 31.25 MHz depths wrap"
    unwrapped = replace(scan, depth=(scan.depth + counts * ambiguity).astype(np.float32), depth_wrapped=False)
    wrapped_run, unwrapped_run = (correct_scan(s, tiny_geometric_model) for s in (scan, unwrapped))
    assert np.array_equal(wrapped_run.flags, unwrapped_run.flags)
    np.testing.assert_allclose(wrapped_run.depth, unwrapped_run.depth, rtol=0, atol=1e-6)
    np.testing.assert_allclose(wrapped_run.measured_depth, unwrapped.depth[-1], rtol=0, atol=1e-6)


@pytest.mark.unit
def test_fused_depths__a_frequency_without_light_is_left_out_as_ideal_fusion_of_the_lit_ones_would():
    from mpi_lidar.physics.noise import NoiseModel

    noise = NoiseModel.for_sensor(SensorConfig(), FREQS)
    rng = np.random.default_rng(4)
    n, snr = 100_000, 5.0
    true_amplitude = np.tile(snr * noise.floor_v2, (n, 1))
    true_amplitude[:, -1] = 0.0  # the highest frequency, the heaviest, gets no light
    quadrature = noise.quadrature_sigma_v2(true_amplitude)
    phasor = true_amplitude + quadrature * (rng.standard_normal((n, 4)) + 1j * rng.standard_normal((n, 4)))
    depth = 5.0 + np.angle(phasor) * noise.metres_per_radian
    fused = noise.fuse(np.hstack([depth, np.abs(phasor)]))
    lit_weight = noise.depth_sigma_m(np.maximum(true_amplitude, 1e-30))[:, :3] ** -2.0
    ideal = (lit_weight * depth[:, :3]).sum(axis=1) / lit_weight.sum(axis=1)
    ratio = np.abs(fused.depth_m - 5.0).mean() / np.abs(ideal - 5.0).mean()
    assert ratio == pytest.approx(1.0, abs=0.05), "within 5 % of inverse-variance fusion of the lit frequencies"
    assert fused.consistent.mean() > 0.98, "the dark frequency's random phase is not read as a disagreement"
    snr = np.abs(phasor) / noise.floor_v2
    lit = (snr >= 3) | (snr >= snr.max(axis=1, keepdims=True) / 2)  # 3 sds, or half the brightest one's
    np.testing.assert_array_equal(fused.dof, lit.sum(axis=1) - 1)
    dark = ~lit[:, -1] & lit[:, :3].all(axis=1)
    assert dark.mean() > 0.9
    first = np.flatnonzero(dark)[0]
    weight = noise.depth_sigma_m(np.abs(phasor[first:first + 1]))[0, :3] ** -2.0
    assert fused.depth_m[first] == pytest.approx((weight * depth[first, :3]).sum() / weight.sum(), abs=1e-6)
    assert fused.sigma_m[first] == pytest.approx(weight.sum() ** -0.5, rel=1e-6)
