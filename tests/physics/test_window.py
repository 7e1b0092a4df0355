"""The integration window's leakage, removed in closed form: checked against the moment model's own mean taps."""

from __future__ import annotations

import numpy as np
import pytest

from mpi_lidar.config import Config, SimulatorConfig
from mpi_lidar.physics.demod import depth_and_amplitude
from mpi_lidar.physics.moments import TAPS_FROM_PQ, MomentSensor
from mpi_lidar.physics.window import window_corrections_m

pytestmark = pytest.mark.unit

RANGES_M = np.linspace(0.3, 11.9, 300)


def mean_measurements(config: Config, albedo: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Noiseless single-path depths (n, F) [m] and amplitudes (n, F) [V^2] over RANGES_M, and the true depths
    wrapped as each frequency wraps them (n, F) [m]."""
    theta = np.zeros((RANGES_M.size, 6))
    theta[:, 0], theta[:, 1], theta[:, 2] = RANGES_M, 1.0, albedo
    mean, _ = MomentSensor(config).quadrature_moments(theta, multipath=False)
    c = config.sensor.speed_of_light_m_per_s
    depth, amplitude = depth_and_amplitude(mean @ TAPS_FROM_PQ.T, config.frequencies_hz, c)
    wrap = c / (2 * np.asarray(config.frequencies_hz))
    return depth, amplitude, np.mod(RANGES_M[:, None], wrap)


def wrapped_error_m(depth: np.ndarray, truth: np.ndarray, config: Config) -> np.ndarray:
    wrap = config.sensor.speed_of_light_m_per_s / (2 * np.asarray(config.frequencies_hz))
    return (depth - truth + wrap / 2) % wrap - wrap / 2


@pytest.mark.parametrize("albedo", [0.7, 0.05])
def test_window_corrections__recover_the_true_depth_of_the_moment_model(albedo):
    config = Config(simulator=SimulatorConfig(round_photons=False))
    depth, amplitude, truth = mean_measurements(config, albedo)
    before = np.abs(wrapped_error_m(depth, truth, config))
    assert before.max() > 2e-4, "the default window leaks: up to 0.6 mm at 12.5 MHz"
    corrected = depth + window_corrections_m(depth, amplitude, tuple(config.frequencies_hz), config.sensor)
    # First order in the leakage (1e-3) and float32 phases: within a micrometre, against 0.3-0.6 mm.
    assert np.abs(wrapped_error_m(corrected, truth, config)).max() < 1e-6


def test_window_corrections__the_error_they_remove_is_the_window_s():
    whole = Config(simulator=SimulatorConfig(round_photons=False, whole_cycles=True))
    depth, _, truth = mean_measurements(whole, 0.7)
    assert np.abs(wrapped_error_m(depth, truth, whole)).max() < 1e-9, "a window of whole cycles does not leak"


def test_window_corrections__are_periodic_in_the_phase_and_nan_where_nothing_is_measured():
    config = Config()
    wrap = config.sensor.speed_of_light_m_per_s / (2 * np.asarray(config.frequencies_hz))
    depth = np.array([[1.0, 1.0, 1.0, 1.0], [np.nan, 2.0, 2.0, 2.0]])
    amplitude = np.full((2, 4), 0.1)
    frequencies = tuple(config.frequencies_hz)
    shifted = window_corrections_m(depth + wrap, amplitude, frequencies, config.sensor)
    np.testing.assert_allclose(shifted, window_corrections_m(depth, amplitude, frequencies, config.sensor), atol=2e-8)
    assert np.isnan(shifted[1, 0]) and np.isfinite(shifted[1, 1:]).all()
