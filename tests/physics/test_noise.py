"""The noise model at a measured amplitude, and the unwrapping of raw rows it weighs."""

from __future__ import annotations

import numpy as np

from mpi_lidar.config import PAPER_FREQUENCIES_HZ, Config, PriorConfig, SensorConfig
from mpi_lidar.physics import make_sensor
from mpi_lidar.physics.demod import unambiguous_range
from mpi_lidar.physics.noise import _moment_quadrature_noise, depth_noise_m, quadrature_noise_v2, unwrapped_rows
from mpi_lidar.simulation.dataset import prior_wraps, simulate_rows

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
