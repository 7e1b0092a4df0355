"""Two-path light transport, paper eq 11-15, against closed forms and the noiseless simulators."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import assume, given, settings
from hypothesis import strategies as st

from mpi_lidar.config import Config
from mpi_lidar.physics import demod, make_sensor
from mpi_lidar.physics.sensor import received_voltage_amplitude
from mpi_lidar.physics.transport import (
    direct_amplitude,
    harmonic_multiples,
    multipath_amplitude,
    path_phasor,
    phasor,
    phasor_sums,
    round_trip_phase,
    two_path_phase_bias,
    two_path_phasors,
)
from mpi_lidar.simulation.sampling import sample_theta

pytestmark = pytest.mark.unit

C = 3.0e8
GAMMA_R = 0.1794
FREQS = np.array([12.5e6, 18.75e6, 25e6, 31.25e6])


def test_direct_amplitude__eq12_inverse_square():
    assert direct_amplitude(GAMMA_R, 1.0, 1.0) == pytest.approx(0.1794, rel=1e-15)
    got = direct_amplitude(GAMMA_R, [0.5, 0.14], [1.4, 2.4])
    np.testing.assert_allclose(got, [0.1794 * 0.5 / 1.96, 0.1794 * 0.14 / 5.76], rtol=1e-15)


def test_multipath_amplitude__eq13_product_of_three_brdfs():
    got = multipath_amplitude(GAMMA_R, [0.5, 1.0], [0.8, 0.0], [0.25, 1.0], [2.0, 1.0])
    np.testing.assert_allclose(got, [0.1794 * 0.5 * 0.8 * 0.25 / 4.0, 0.0], rtol=1e-15, atol=0)


def test_round_trip_phase__half_range_is_pi():
    # at 31.25 MHz the unambiguous range is c / 2f = 4.8 m: d = 2.4 m is exactly phi = pi
    assert round_trip_phase(31.25e6, 2.4, C) == pytest.approx(np.pi, rel=1e-15)
    np.testing.assert_allclose(round_trip_phase(FREQS, C / (2 * FREQS), C), 2 * np.pi, rtol=1e-15)


def test_path_phasor__positive_exponent_of_the_round_trip_phase():
    depth = np.array([[0.3], [1.7], [2.4]])
    got = path_phasor(0.5, depth, FREQS, C)
    np.testing.assert_array_equal(got, 0.5 * np.exp(1j * round_trip_phase(FREQS, depth, C)))
    np.testing.assert_array_equal(got, phasor(0.5, round_trip_phase(FREQS, depth, C)))
    assert got.shape == (3, 4)
    # at 31.25 MHz, 1.2 m is a quarter of the 4.8 m range: +90 degrees
    assert path_phasor(2.0, 1.2, 31.25e6, C) == pytest.approx(2j, abs=1e-15)


def test_path_phasor__is_what_the_demodulation_reads_back(noiseless):
    """The sign convention matches eq 5-7: the taps of a path's phasor demodulate to the path's own depth
    (the conjugate would give the range minus the depth)."""
    config = noiseless(whole_cycles=True)
    s = config.sensor
    depth = np.array([0.4, 1.1, 1.9, 2.35])
    gamma = 0.05
    to_volts = received_voltage_amplitude(1.0, s.modulation_contrast, s.demodulation_amplitude_v)
    z = path_phasor(gamma * to_volts, depth[:, None], FREQS[None, :], s.speed_of_light_m_per_s)
    taps = make_sensor(config).taps_from_phasors(np.full(z.shape, gamma * to_volts), z, np.random.default_rng(0))
    got, amplitude = demod.depth_and_amplitude(taps, FREQS, s.speed_of_light_m_per_s)
    np.testing.assert_allclose(got, np.broadcast_to(depth[:, None], got.shape), rtol=0, atol=1e-9)
    np.testing.assert_allclose(amplitude, gamma, rtol=1e-9)


def test_two_path_phasors__shapes_and_closed_forms(rng):
    theta = sample_theta(Config().prior, 7, rng)
    gamma_d, phi_d, gamma_m, phi_m = two_path_phasors(theta, FREQS, GAMMA_R, C)
    for array in (gamma_d, phi_d, gamma_m, phi_m):
        assert array.shape == (7, 4)
    d_as, d_ab, rho_sas, rho_sab, rho_aba, rho_bas = theta.T
    np.testing.assert_allclose(gamma_d, (GAMMA_R * rho_sas / d_as**2)[:, None] * np.ones(4), rtol=1e-14)
    np.testing.assert_allclose(gamma_m, (GAMMA_R * rho_sab * rho_aba * rho_bas / d_as**2)[:, None] * np.ones(4),
                               rtol=1e-14)
    np.testing.assert_allclose(phi_d, 4 * np.pi * FREQS * d_as[:, None] / C, rtol=1e-14)
    np.testing.assert_allclose(phi_m - phi_d, 4 * np.pi * FREQS * d_ab[:, None] / C, rtol=1e-9, atol=1e-12)


def test_two_path_phasors__multipath_false_drops_the_second_path(rng):
    theta = sample_theta(Config().prior, 5, rng)
    with_mp = two_path_phasors(theta, FREQS, GAMMA_R, C)
    without = two_path_phasors(theta, FREQS, GAMMA_R, C, multipath=False)
    assert np.all(with_mp[2] > 0)
    np.testing.assert_array_equal(without[2], 0.0)
    for a, b in zip((with_mp[0], with_mp[1], with_mp[3]), (without[0], without[1], without[3]), strict=True):
        np.testing.assert_array_equal(a, b)


@settings(max_examples=50, deadline=None, derandomize=True)
@given(ratio=st.floats(0.0, 50.0), delta_phase=st.floats(-2 * np.pi, 2 * np.pi))
def test_two_path_phase_bias__equals_argument_of_phasor_sum(ratio, delta_phase):
    total = 1 + ratio * np.exp(1j * delta_phase)
    assume(abs(total) > 1e-6)  # arg(0) is undefined
    got = two_path_phase_bias(ratio, delta_phase)
    assert -np.pi <= got <= np.pi
    difference = np.angle(np.exp(1j * (got - np.angle(total))))
    assert abs(difference) < 1e-9


def test_two_path_phase_bias__limits():
    assert two_path_phase_bias(0.0, 1.0) == 0.0
    assert two_path_phase_bias(0.7, 0.0) == 0.0
    # small r: bias ~ r sin(dphi)
    assert two_path_phase_bias(1e-6, 0.3) == pytest.approx(1e-6 * np.sin(0.3), rel=1e-5)
    # r >> 1: the sum follows the multipath phase, also beyond pi/2 (a plain atan would be off by pi)
    assert two_path_phase_bias(1e6, 2.0) == pytest.approx(2.0, abs=1e-5)
    # equal amplitudes: the phase lies halfway
    assert two_path_phase_bias(1.0, 0.8) == pytest.approx(0.4, rel=1e-12)


def _expected_two_path_depth(theta: np.ndarray, config: Config) -> np.ndarray:
    s = config.sensor
    freqs = np.asarray(config.frequencies_hz)
    gamma_d, phi_d, gamma_m, phi_m = two_path_phasors(theta, freqs, s.gamma_r_v2, s.speed_of_light_m_per_s)
    bias = two_path_phase_bias(gamma_m / gamma_d, phi_m - phi_d)
    return np.mod(phi_d + bias, 2 * np.pi) * s.speed_of_light_m_per_s / (4 * np.pi * freqs)


@settings(max_examples=30, deadline=None, derandomize=True)
@given(seed=st.integers(0, 2**32 - 1), scheme=st.sampled_from(["reciprocal", "independent"]))
def test_two_path_phase_bias__predicts_noiseless_moment_depth(seed, scheme):
    config = Config().replace(simulator={"noise_scale": 0, "round_photons": False, "whole_cycles": True},
                              prior={"scheme": scheme})
    theta = sample_theta(config.prior, 25, np.random.default_rng(seed))
    depth, _ = make_sensor(config).measure(theta, np.random.default_rng(0))
    np.testing.assert_allclose(depth, _expected_two_path_depth(theta, config), rtol=0, atol=1e-6)


def test_two_path_phase_bias__predicts_noiseless_waveform_depth():
    config = Config().replace(simulator={"noise_scale": 0, "round_photons": False, "whole_cycles": True,
                                         "fidelity": "waveform"})
    theta = sample_theta(config.prior, 12, np.random.default_rng(3))
    depth, _ = make_sensor(config).measure(theta, np.random.default_rng(0))
    expected = _expected_two_path_depth(theta, config)
    np.testing.assert_allclose(depth, expected, rtol=0, atol=1e-6)
    # the multipath bias itself is millimetres, far above the tolerance: the comparison is not vacuous
    assert np.abs(expected - theta[:, :1]).max() > 1e-3


def test_harmonic_multiples__whole_multiples_of_a_common_frequency_or_none():
    base, multiples = harmonic_multiples(FREQS)
    assert base == pytest.approx(6.25e6, rel=1e-12) and multiples.tolist() == [2, 3, 4, 5]
    assert harmonic_multiples([20e6, 10e6])[1].tolist() == [2, 1], "any order"
    assert harmonic_multiples([10e6, 10e6 * np.pi]) is None, "incommensurate"
    assert harmonic_multiples([10e6, 90e6]) is None, "a multiple past 8: exponentials are cheaper than powers"
    assert harmonic_multiples([10e6, 10e6 + 1.0]) is None, "1 Hz apart is not a multiple"


@pytest.mark.parametrize("freqs", [FREQS, np.array([10e6, 10e6 * np.pi, 31e6]), np.array([15e6])])
def test_phasor_sums__equal_the_sum_of_the_weighted_path_phasors(freqs):
    rng = np.random.default_rng(3)
    depth, weights = rng.uniform(0.0, 40.0, (7, 300)), rng.uniform(0.0, 1.0, (7, 300))
    expected = np.array([[np.sum(w * path_phasor(1.0, d, f, C)) for f in freqs] for w, d in zip(weights, depth,
                                                                                                   strict=True)])
    sums = phasor_sums(weights, depth, freqs, C)
    assert sums.shape == (7, freqs.size)
    np.testing.assert_allclose(sums, expected, rtol=0, atol=1e-12 * np.abs(weights).sum(1).max())
