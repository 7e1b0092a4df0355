"""The noise model at a measured amplitude, and the unwrapping of raw rows it weighs."""

from __future__ import annotations

import numpy as np
import pytest

from mpi_lidar.config import PAPER_FREQUENCIES_HZ, Config, PriorConfig, SensorConfig
from mpi_lidar.physics import make_sensor
from mpi_lidar.physics.demod import unambiguous_range
from mpi_lidar.physics.noise import (
    NoiseModel,
    _moment_quadrature_noise,
    depth_noise_m,
    quadrature_noise_v2,
    unwrapped_rows,
)
from mpi_lidar.simulation.dataset import prior_wraps, simulate_rows

pytestmark = pytest.mark.unit

SENSOR = SensorConfig()


def test_quadrature_noise_v2__equals_the_moment_models_covariance_at_any_amplitude():
    amplitude = np.random.default_rng(0).uniform(0.0, 0.8, (500, 4))
    np.testing.assert_allclose(quadrature_noise_v2(SENSOR, PAPER_FREQUENCIES_HZ, amplitude),
                               _moment_quadrature_noise(SENSOR, PAPER_FREQUENCIES_HZ, amplitude), rtol=1e-12)


def test_unwrapped_rows__a_wall_at_6_m_comes_back_in_one_range_with_its_amplitudes():
    theta = np.tile([[6.0, 0.0, 0.7, 0.7, 0.0, 0.7]], (2000, 1))
    depth, amplitude = make_sensor(Config()).measure(theta, np.random.default_rng(1))
    raw = np.hstack([depth, amplitude]).astype(np.float32)
    assert (raw[:, 3] < 1.3).all(), "31.25 MHz wraps at 4.8 m"
    rows, confidence = unwrapped_rows(raw, PAPER_FREQUENCIES_HZ, SENSOR)
    sigma = depth_noise_m(SENSOR, PAPER_FREQUENCIES_HZ, amplitude)  # 10-25 mm at 6 m
    assert (np.abs(rows[:, :4] - 6.0) < 5 * sigma).all()
    np.testing.assert_array_equal(rows[:, 4:], raw[:, 4:])
    assert confidence.min() > 0.999


def test_unwrapped_rows__depths_that_need_no_count_keep_their_bytes():
    theta = np.tile([[2.0, 0.05, 0.5, 0.5, 0.3, 0.5]], (500, 1))
    depth, amplitude = make_sensor(Config()).measure(theta, np.random.default_rng(2))
    raw = np.hstack([depth, amplitude]).astype(np.float32)
    rows, _ = unwrapped_rows(raw, PAPER_FREQUENCIES_HZ, SENSOR)
    assert rows.tobytes() == raw.tobytes()


def test_simulate_rows__a_prior_past_the_wrap_gives_unwrapped_depths_one_within_it_does_not_unwrap():
    far = Config().replace(prior={"d_as_m": (5.0, 11.0)})
    assert prior_wraps(far) and prior_wraps(Config()) and not prior_wraps(Config(prior=PriorConfig()))
    rows, theta = simulate_rows(far, 3000, np.random.default_rng(3))
    ambiguity = unambiguous_range(np.asarray(PAPER_FREQUENCIES_HZ), SENSOR.speed_of_light_m_per_s)
    assert (theta[:, 0] > ambiguity[-1]).mean() > 0.9
    wrong = np.abs(rows[:, 3] - theta[:, 0]) > ambiguity[-1] / 2
    assert wrong.mean() < 0.01, "nearly every row unwrapped to its own range"


# --- the noise model object -------------------------------------------------------------------------------


def test_noise_model__depth_sigma_is_the_law_in_closed_form():
    """sigma_f = eta sqrt(a_f + b_f A) / A * c / (4 pi f), written out from the coefficients."""
    noise = NoiseModel.for_sensor(SENSOR, PAPER_FREQUENCIES_HZ, noise_scale=2.5)
    amplitude = np.array([[0.001, 0.01, 0.1, 0.5]])
    expected = (2.5 * np.sqrt(noise.read_variance_v4 + noise.shot_variance_v2 * amplitude) / amplitude
                * SENSOR.speed_of_light_m_per_s / (4 * np.pi * np.asarray(PAPER_FREQUENCIES_HZ)))
    np.testing.assert_allclose(noise.depth_sigma_m(amplitude), expected, rtol=1e-12)
    np.testing.assert_allclose(noise.floor_v2, 2.5 * np.sqrt(noise.read_variance_v4), rtol=1e-12)


def test_noise_model__the_sensor_law_at_scale_one_is_the_module_functions_to_the_bit():
    amplitude = np.random.default_rng(3).uniform(1e-4, 0.8, (200, 4))
    noise = NoiseModel.for_sensor(SENSOR, PAPER_FREQUENCIES_HZ)
    assert noise.depth_sigma_m(amplitude).tobytes() == depth_noise_m(SENSOR, PAPER_FREQUENCIES_HZ, amplitude).tobytes()
    assert noise.scaled(3.0).noise_scale == 3.0 and noise.noise_scale == 1.0


def test_noise_model__a_noise_scale_widens_the_sds_and_the_consistency_test_not_the_mean():
    rng = np.random.default_rng(4)
    noise = NoiseModel.for_sensor(SENSOR, PAPER_FREQUENCIES_HZ)
    amplitude = np.full((20_000, 4), 0.01)
    noisier = noise.scaled(2.0)
    depth = 2.0 + rng.standard_normal((20_000, 4)) * noisier.depth_sigma_m(amplitude)
    raw = np.hstack([depth, amplitude])
    plain, scaled = noise.fuse(raw), noisier.fuse(raw)
    np.testing.assert_array_equal(plain.depth_m, scaled.depth_m)
    np.testing.assert_allclose(scaled.sigma_m, 2 * plain.sigma_m, rtol=1e-6)
    # Noise twice the model's: the model at scale 1 calls far more pixels inconsistent than the 0.1 % p-value.
    assert (~plain.consistent).mean() > 0.2 and (~scaled.consistent).mean() < 0.003
    np.testing.assert_allclose(noisier.chi2(raw), 3 * scaled.birge_ratio.astype(np.float64) ** 2, rtol=1e-12)


def test_noise_model__unwrapping_with_a_scale_keeps_the_counts_and_lowers_the_confidence():
    theta = np.tile([[9.0, 0.0, 0.3, 0.3, 0.0, 0.3]], (3000, 1))
    depth, amplitude = make_sensor(Config()).measure(theta, np.random.default_rng(5))
    raw = np.hstack([depth, amplitude]).astype(np.float32)
    noise = NoiseModel.for_sensor(SENSOR, PAPER_FREQUENCIES_HZ)
    rows, confidence = noise.unwrap(raw)
    _, doubted = noise.scaled(30.0).unwrap(raw)
    assert np.median(np.abs(rows[:, 3] - 9.0)) < 0.05
    assert doubted.mean() < confidence.mean() - 0.01, "30 times the noise: the wrap counts are less certain"
    _, equal = noise.unwrap(raw, equal_amplitudes=True)
    assert equal.shape == (3000,)
