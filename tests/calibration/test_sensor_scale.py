"""The sensor-scale estimator (mpi_lidar.calibration.sensor_scale): against residuals drawn from the noise model,
then through a scan's flat surfaces on rendered boards in other amplitude units."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from scipy import stats

from mpi_lidar.calibration.sensor_scale import (
    SensorScale,
    estimate_sensor_scale,
    gaussian_t_scale,
    measure_sensor_scale,
)
from mpi_lidar.config import PAPER_FREQUENCIES_HZ, Config
from mpi_lidar.correction import CorrectionOptions, analyse_geometry, depth_noise_m, validity_flags
from mpi_lidar.correction.validity import depth_rules_only, usable_depth_of
from mpi_lidar.physics.noise import NoiseModel
from mpi_lidar.simulation.scenes import corner, flat_wall, render
from tests.calibration.rendered_scenes import DEPTH_RULES, SENSOR, boards_scene, depth_usable, in_units, rendered

FREQS = PAPER_FREQUENCIES_HZ


# --- synthetic residuals from the noise model ----------------------------------------------------------------


def model_residuals(rng: np.random.Generator, pixels: int, low_v2: float, high_v2: float, noise_scale: float,
                    offsets_m: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Amplitudes (n, F) [V^2], log-uniform in [low, high] (each frequency within 10 % of the pixel's), and residuals
    (n, F) [m] drawn as N(offset_f, (noise_scale sd_f)^2) with the noise model's sd_f."""
    level = np.exp(rng.uniform(np.log(low_v2), np.log(high_v2), pixels))
    amplitude = level[:, None] * rng.uniform(0.9, 1.1, (pixels, 4))
    sd = depth_noise_m(SENSOR, FREQS, amplitude)
    return amplitude, offsets_m + noise_scale * sd * rng.standard_normal(amplitude.shape)


@pytest.mark.unit
def test_gaussian_t_scale__is_the_t_fit_of_a_large_gaussian_sample():
    sample = np.random.default_rng(0).standard_normal(100_000)
    _, _, scale = stats.t.fit(sample, f0=6.0, floc=0.0)
    # The scale's standard error at 1e5 draws is about 0.3 %.
    assert gaussian_t_scale(6.0) == pytest.approx(scale, rel=0.01)
    assert gaussian_t_scale(1e6) == pytest.approx(1.0, abs=1e-5)  # the t of infinite degrees is the Gaussian


@pytest.mark.unit
@pytest.mark.parametrize("units_per_v2", [1.0, 4000.0, 0.01])
def test_estimate_sensor_scale__recovers_scales_and_offsets_of_the_noise_model(units_per_v2):
    offsets_m = np.array([3e-3, 1e-3, 0.0, -0.5e-3])
    amplitude, residual = model_residuals(np.random.default_rng(1), 6000, 0.003, 0.5, 1.5, offsets_m)
    found = estimate_sensor_scale(amplitude * units_per_v2, residual, FREQS, SENSOR)
    assert found.significant and found.reason == "" and found.pixels == 6000 and found.outliers == 0
    assert found.amplitude_scale == pytest.approx(units_per_v2, rel=0.1)
    assert abs(found.amplitude_scale - units_per_v2) < 3 * found.amplitude_scale_sigma
    assert abs(found.noise_scale - 1.5) < 3 * found.noise_scale_sigma and found.noise_scale_sigma < 0.05
    np.testing.assert_array_less(np.abs(found.offsets_m - (offsets_m - offsets_m[-1])),
                                 3 * found.offsets_sigma_m + 1e-12)
    assert found.offsets_m[-1] == 0.0 and found.offsets_sigma_m[-1] < 1e-9  # the reference frequency
    # The 5th to 95th percentile of a log-uniform amplitude: 90 % of its decades.
    assert found.amplitude_decades == pytest.approx(0.9 * np.log10(0.5 / 0.003), abs=0.05)


@pytest.mark.unit
def test_estimate_sensor_scale__the_amplitude_unit_changes_the_scale_alone():
    amplitude, residual = model_residuals(np.random.default_rng(2), 3000, 0.003, 0.5, 1.0, np.zeros(4))
    volts = estimate_sensor_scale(amplitude, residual, FREQS, SENSOR)
    units = estimate_sensor_scale(amplitude * 4000, residual, FREQS, SENSOR)
    # Equivariance: the likelihood depends on lambda only through amplitude / lambda.
    assert units.amplitude_scale / 4000 == pytest.approx(volts.amplitude_scale, rel=1e-4)
    assert units.noise_scale == pytest.approx(volts.noise_scale, rel=1e-4)
    assert units.amplitude_scale_sigma / units.amplitude_scale == pytest.approx(
        volts.amplitude_scale_sigma / volts.amplitude_scale, rel=1e-2)


@pytest.mark.integration
@pytest.mark.slow
def test_estimate_sensor_scale__sigmas_match_the_scatter_over_draws():
    pulls = []
    for seed in range(16):
        amplitude, residual = model_residuals(np.random.default_rng(100 + seed), 1500, 0.003, 0.5, 1.2, np.zeros(4))
        found = estimate_sensor_scale(amplitude * 50, residual, FREQS, SENSOR)
        pulls.append([(found.amplitude_scale - 50) / found.amplitude_scale_sigma,
                      (found.noise_scale - 1.2) / found.noise_scale_sigma,
                      found.offsets_m[0] / found.offsets_sigma_m[0]])
    spread = np.std(pulls, axis=0, ddof=1)
    # 16 draws know a standard deviation to about 18 %: calibrated sigmas give pulls of spread 1 within that.
    np.testing.assert_array_less(spread, 1.5)
    np.testing.assert_array_less(0.6, spread)
    np.testing.assert_array_less(np.abs(np.mean(pulls, axis=0)), 0.8)


@pytest.mark.unit
def test_estimate_sensor_scale__one_amplitude_determines_only_a_product():
    amplitude, residual = model_residuals(np.random.default_rng(3), 4000, 0.03, 0.035, 1.0, np.zeros(4))
    free = estimate_sensor_scale(amplitude * 4000, residual, FREQS, SENSOR)
    assert not free.significant
    assert "too narrow to tell the amplitude scale from the noise scale" in free.reason
    assert "fix_noise_scale=1" in free.reason and abs(free.scale_noise_correlation) > 0.99
    fixed = estimate_sensor_scale(amplitude * 4000, residual, FREQS, SENSOR, fix_noise_scale=1.0)
    assert fixed.significant and fixed.noise_scale == 1.0 and fixed.noise_scale_sigma == 0.0
    assert fixed.amplitude_scale == pytest.approx(4000, rel=0.1)
    assert abs(fixed.amplitude_scale - 4000) < 3 * fixed.amplitude_scale_sigma


@pytest.mark.unit
def test_estimate_sensor_scale__too_few_pixels_measure_nothing():
    amplitude, residual = model_residuals(np.random.default_rng(4), 150, 0.003, 0.5, 1.0, np.zeros(4))
    residual[:20, 1] = np.nan  # rows without a residual do not count
    found = estimate_sensor_scale(amplitude, residual, FREQS, SENSOR)
    assert not found.significant and found.pixels == 130 and found.reason == "only 130 flat pixels, at least 200 needed"
    assert np.isnan(found.amplitude_scale) and found.amplitude_scale_sigma == np.inf
    assert np.isnan(found.offsets_m).all() and found.offsets_m.shape == (4,)


@pytest.mark.unit
def test_estimate_sensor_scale__gross_outliers_at_low_amplitude_are_left_out():
    rng = np.random.default_rng(5)
    amplitude, residual = model_residuals(rng, 6000, 0.005, 0.5, 1.0, np.zeros(4))
    dark = np.flatnonzero(amplitude[:, 0] < 0.02)[:150]
    # Pixels of another surface: off the plane by 5 cm to 1 m in every frequency, all at the dark end.
    residual[dark] += rng.choice([-1.0, 1.0], (dark.size, 1)) * rng.uniform(0.05, 1.0, (dark.size, 1))
    found = estimate_sensor_scale(amplitude * 4000, residual, FREQS, SENSOR)
    assert found.outliers == dark.size and found.pixels == 6000 - dark.size and found.significant
    assert found.amplitude_scale == pytest.approx(4000, rel=0.1)
    assert abs(found.noise_scale - 1.0) < 3 * found.noise_scale_sigma


def plane_fit_residuals(rng: np.random.Generator, blocks: int, side: int, low_v2: float, high_v2: float
                        ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Amplitudes (n, F) [V^2] of blocks of side x side pixels, log-uniform in [low, high]; residuals (n, F) [m] of
    model noise from least-squares planes over each block's mean depth over the frequencies; and each pixel's
    leverage (n,), all worked out with numpy's own least squares."""
    row, column = np.divmod(np.arange(side * side), side)
    design = np.column_stack([np.ones(side * side), row, column])
    hat = design @ np.linalg.pinv(design)
    level = np.exp(rng.uniform(np.log(low_v2), np.log(high_v2), blocks))
    amplitude = np.repeat(level, side * side)[:, None] * rng.uniform(0.9, 1.1, (blocks * side * side, 4))
    tilt = rng.normal(0.0, 0.01, (blocks, 3)) @ design.T  # any plane: the fit takes it up exactly
    noise = depth_noise_m(SENSOR, FREQS, amplitude) * rng.standard_normal(amplitude.shape)
    depth = (2.0 + tilt.reshape(-1))[:, None] + noise
    mean = depth.mean(1).reshape(blocks, side * side)
    plane = (mean @ hat.T).reshape(-1)
    return amplitude, depth - plane[:, None], np.tile(np.diag(hat), blocks)


@pytest.mark.unit
def test_estimate_sensor_scale__leverage_corrects_the_degrees_of_freedom_of_the_planes():
    # 3 x 3 blocks, a leverage of 1/3 per pixel, in the thermal regime: with the noise scale fixed, the amplitude
    # scale reads the residuals' overall variance one to one (sd ~ lambda eta / A), to a few per mille.
    amplitude, residual, leverage = plane_fit_residuals(np.random.default_rng(6), 1500, 3, 0.002, 0.005)
    assert leverage.mean() == pytest.approx(1 / 3, rel=1e-12)
    corrected = estimate_sensor_scale(amplitude, residual, FREQS, SENSOR, leverage=leverage, fix_noise_scale=1.0)
    plain = estimate_sensor_scale(amplitude, residual, FREQS, SENSOR, fix_noise_scale=1.0)
    assert corrected.amplitude_scale_sigma < 0.006
    assert abs(corrected.amplitude_scale - 1.0) < 3 * corrected.amplitude_scale_sigma
    # (S1) left out: the fit shrinks the residual variance of the noisiest frequency by 13 % and raises the least
    # noisy one's by 7 %; on balance the noise reads 2 % low, and so does the amplitude scale, by 6 sigmas.
    assert abs(plain.amplitude_scale - 1.0) > 3 * plain.amplitude_scale_sigma


@pytest.mark.unit
def test_estimate_sensor_scale__refuses_mismatched_shapes():
    with pytest.raises(ValueError, match="same shape"):
        estimate_sensor_scale(np.ones((10, 4)), np.ones((12, 4)), FREQS, SENSOR)
    with pytest.raises(ValueError, match="leverage"):
        estimate_sensor_scale(np.ones((10, 4)), np.ones((10, 4)), FREQS, SENSOR, leverage=np.zeros(3))
    with pytest.raises(ValueError, match="fix_noise_scale"):
        estimate_sensor_scale(np.ones((10, 4)), np.ones((10, 4)), FREQS, SENSOR, fix_noise_scale=0.0)


@pytest.mark.unit
def test_sensor_scale__is_frozen():
    found = estimate_sensor_scale(np.ones((5, 4)), np.zeros((5, 4)), FREQS, SENSOR)
    with pytest.raises(dataclasses.FrozenInstanceError):
        found.noise_scale = 2.0  # type: ignore[misc]
    assert isinstance(found, SensorScale)


# --- rendered scenes --------------------------------------------------------------------------------------------


@pytest.mark.integration
@pytest.mark.slow
@pytest.mark.parametrize("units_per_v2", [1.0, 4000.0, 0.01])
def test_measure_sensor_scale__reads_the_boards_amplitude_unit(units_per_v2):
    scan = in_units(rendered(boards_scene()), units_per_v2)
    found = measure_sensor_scale(scan, depth_usable(scan), DEPTH_RULES, SENSOR)
    assert found.significant and found.pixels > 15_000 and found.amplitude_decades > 1.3
    assert found.amplitude_scale == pytest.approx(units_per_v2, rel=0.1)
    assert abs(found.amplitude_scale - units_per_v2) < 3 * found.amplitude_scale_sigma
    assert found.noise_scale == pytest.approx(1.0, rel=0.1)


@pytest.mark.integration
@pytest.mark.slow
def test_measure_sensor_scale__reads_the_simulators_noise_scale():
    scan = in_units(rendered(boards_scene(), noise_scale=2.0), 4000.0)
    found = measure_sensor_scale(scan, depth_usable(scan), DEPTH_RULES, SENSOR)
    assert found.significant
    assert found.noise_scale == pytest.approx(2.0, rel=0.1)
    assert abs(found.noise_scale - 2.0) < 3 * found.noise_scale_sigma
    assert found.amplitude_scale == pytest.approx(4000.0, rel=0.1)


@pytest.mark.integration
@pytest.mark.slow
def test_measure_sensor_scale__recovers_added_offsets_relative_to_the_highest_frequency():
    # Whole-cycle windows: the simulator's own window error (up to 0.6 mm at 12.5 MHz, varying with depth) is gone.
    scan = rendered(boards_scene(), whole_cycles=True)
    added_m = np.array([3e-3, 0.0, -1e-3, 0.5e-3])
    shifted = dataclasses.replace(scan, depth=(scan.depth + added_m[:, None, None]).astype(np.float32))
    usable = depth_usable(shifted)
    scene = analyse_geometry(shifted, usable, CorrectionOptions(footprint_area_m2=0.04), SENSOR)
    found = measure_sensor_scale(shifted, usable, CorrectionOptions(footprint_area_m2=0.04), SENSOR, scene=scene)
    expected = added_m - added_m[-1]
    np.testing.assert_array_less(np.abs(found.offsets_m - expected), 3 * found.offsets_sigma_m + 1e-12)
    np.testing.assert_array_less(found.offsets_sigma_m[:3], 0.05e-3)
    # The scene's blocks reused give what the scan's own give.
    again = measure_sensor_scale(shifted, usable, CorrectionOptions(footprint_area_m2=0.04), SENSOR)
    np.testing.assert_allclose(again.offsets_m, found.offsets_m, atol=1e-12)


@pytest.mark.unit
def test_measure_sensor_scale__a_wall_of_one_amplitude_gives_the_scale_only_with_the_noise_fixed():
    scan = in_units(rendered(flat_wall(height=48, width=64)), 4000.0)
    found = measure_sensor_scale(scan, depth_usable(scan), DEPTH_RULES, SENSOR)
    assert found.pixels > 2000 and found.amplitude_decades < 0.1
    assert not found.significant and "too narrow to tell the amplitude scale from the noise scale" in found.reason
    fixed = measure_sensor_scale(scan, depth_usable(scan), DEPTH_RULES, SENSOR, fix_noise_scale=1.0)
    assert fixed.significant and fixed.amplitude_scale == pytest.approx(4000.0, rel=0.1)


@pytest.mark.unit
def test_measure_sensor_scale__a_corner_has_too_few_flat_pixels():
    scan = rendered(corner(90.0, 2.0, 0.8, height=24, width=32))
    found = measure_sensor_scale(scan, depth_usable(scan), DEPTH_RULES, SENSOR)
    assert not found.significant and found.pixels < 200
    assert found.reason.startswith(f"only {found.pixels} flat pixels")


@pytest.mark.unit
def test_measure_sensor_scale__with_the_window_s_leakage_removed_a_wall_s_offsets_are_noise():
    scan = render(flat_wall(20.0, 1.0, 0.7, height=96, width=128), Config(), np.random.default_rng(0))
    raw, options = scan.raw_pixels(), CorrectionOptions()
    noise = NoiseModel.for_sensor(SENSOR, scan.frequencies_hz)
    by_depth = usable_depth_of(raw, validity_flags(raw, depth_rules_only(options), noise))
    as_they_are = measure_sensor_scale(scan, by_depth, options, SENSOR, fix_noise_scale=1.0)
    windowed = measure_sensor_scale(scan, by_depth, options, SENSOR, fix_noise_scale=1.0, window=True)
    assert as_they_are.significant and windowed.significant
    assert as_they_are.offsets_m[0] < -0.3e-3, "the leakage at 12.5 MHz, 1 m: -0.4 mm relative to 31.25 MHz"
    assert (np.abs(windowed.offsets_m) <= 4 * windowed.offsets_sigma_m + 1e-12).all(), windowed.offsets_m


@pytest.mark.unit
def test_measure_sensor_scale__a_scan_without_geometry_measures_nothing():
    bare = dataclasses.replace(rendered(boards_scene()), azimuth_rad=None, elevation_rad=None)
    found = measure_sensor_scale(bare, depth_usable(bare), CorrectionOptions(), SENSOR)
    assert not found.significant and found.reason == "only 0 flat pixels, at least 200 needed"
    assert found.pixels == 0 and np.isnan(found.amplitude_scale) and found.offsets_m.shape == (4,)
