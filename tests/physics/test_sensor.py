"""Detector chain (paper eq 16-30), the calibration that makes Table I self-consistent, and the noiseless sensor."""

from __future__ import annotations

import numpy as np
import pytest
from scipy import stats

from mpi_lidar.config import Config
from mpi_lidar.physics import FIDELITIES, make_sensor
from mpi_lidar.physics.moments import MomentSensor
from mpi_lidar.physics.sensor import (
    DetectorChain,
    SensorModel,
    WaveformSensor,
    dark_electrons,
    photon_energy,
    received_power,
    received_voltage_amplitude,
    thermal_noise_current,
    tia_noise_electron_variance,
)
from mpi_lidar.physics.transport import two_path_phasors
from mpi_lidar.simulation.sampling import sample_theta

pytestmark = pytest.mark.unit

C = 3.0e8
FREQS = np.array([12.5e6, 18.75e6, 25e6, 31.25e6])
RANGES = C / (2 * FREQS)
BOLTZMANN = 1.380649e-23
Q = 1.60217663e-19


def chain(**simulator: object) -> DetectorChain:
    config = Config().replace(simulator=simulator)
    return DetectorChain.from_config(config.sensor, config.simulator)


# --- calibration reference values ----------------------------------------------------------------------


def test_photon_energy__eq17_reference_value():
    assert photon_energy(6.62606896e-34, C, 852e-9) == pytest.approx(2.3331e-19, rel=5e-5)


def test_received_voltage_amplitude__reference_point_is_0p7498_v():
    # R = 2 Gamma / (alpha m) with Gamma = gamma_r rho / d^2 = 0.1794 V^2 at rho = 1, d = 1 m
    assert received_voltage_amplitude(0.1794, 1.0, 0.4785) == pytest.approx(0.7498, abs=1e-4)
    assert received_voltage_amplitude(0.1794, 0.5, 0.4785) == pytest.approx(2 * 0.7498, abs=2e-4)


def test_detector_chain__volts_per_photon_is_4p4727e_5(config):
    g = DetectorChain.from_config(config.sensor, config.simulator).volts_per_photon
    assert g == pytest.approx(4.4727e-5, abs=1e-9)
    assert g == pytest.approx(0.67 * 50.0 * Q * 50e3 / 6e-9, rel=1e-12)


def test_photon_waveforms__16765_photons_per_bin_at_reference_point(config, scene):
    waveform = make_sensor(config).photon_waveforms(scene(1.0, rho_sas=1.0), multipath=False)[0]
    assert waveform.constant[0] == pytest.approx(16765, abs=1)
    assert waveform.peak[0] == pytest.approx(2 * 16765, abs=2)  # alpha = 1: the waveform swings 0..2R
    assert np.hypot(waveform.cosine, waveform.sine)[0] == pytest.approx(waveform.constant[0], rel=1e-12)


def test_received_power__0p652_uw_at_reference_point(config):
    s = config.sensor
    energy = photon_energy(s.planck_j_s, s.speed_of_light_m_per_s, s.wavelength_m)
    assert received_power(16765, energy, s.transit_time_s) == pytest.approx(0.652e-6, abs=0.5e-9)


def test_sensor_model__integration_window_is_2667_bins(config):
    assert make_sensor(config).bins == [2667] * 4


def test_thermal_noise_current__6p40_mv_per_bin(config):
    s = config.sensor
    current = thermal_noise_current(s.boltzmann_j_per_k, s.temperature_k, s.bandwidth_hz, s.load_resistance_ohm)
    assert current == pytest.approx(np.sqrt(4 * BOLTZMANN * 297.0 * 50e6 / 50.0), rel=1e-12)
    assert current * s.tia_gain_v_per_a == pytest.approx(6.40e-3, abs=0.005e-3)
    assert chain().thermal_v_std == pytest.approx(6.40e-3, abs=0.005e-3)


def test_tia_noise_electron_variance__550_electrons_is_0p73_mv(config):
    s = config.sensor
    variance = tia_noise_electron_variance(s.transit_time_s, s.tia_noise_psd_a2_per_hz, s.bandwidth_hz,
                                           s.electron_charge_c)
    assert np.sqrt(variance) == pytest.approx(550, abs=0.5)
    assert np.sqrt(variance) * Q * 50e3 / 6e-9 == pytest.approx(0.73e-3, abs=0.005e-3)


def test_dark_electrons__zero_at_table_i(config):
    assert dark_electrons(config.sensor) == 0.0


def test_dark_electrons__eq25_closed_form_when_large(config):
    sensor = config.sensor.model_copy(update={"dark_current_fom_a_per_m2": 100.0})
    exponent = -1.1116 * 1.602176634e-19 / (2 * BOLTZMANN * 297.0)
    charge = 0.7854e-6 * 100.0 * 297.0**1.5 * 6e-9 * np.exp(exponent)
    expected = round(charge / Q)
    assert expected >= 3
    assert dark_electrons(sensor) == expected


def test_detector_chain__variance_per_photon_is_eq21():
    c = chain()
    per_electron = Q * 50e3 / 6e-9
    assert c.variance_per_photon_v2 == pytest.approx(per_electron**2 * 50.0**2 * 0.67 * (0.67 + 4.862), rel=1e-12)
    np.testing.assert_allclose(c.bin_voltage_variance([0.0, 30.0, 16765.0]) - c.bin_voltage_variance(0.0),
                               np.array([0.0, 30.0, 16765.0]) * c.variance_per_photon_v2, rtol=1e-12)
    assert chain(noise_scale=0.5).variance_per_photon_v2 == pytest.approx(0.25 * c.variance_per_photon_v2,
                                                                          rel=1e-12)


def test_detector_chain__signal_free_variance_is_thermal_plus_tia_at_table_i():
    c = chain()
    expected = (6.40354e-3) ** 2 + (550.0 * Q * 50e3 / 6e-9) ** 2
    assert c.signal_free_variance_v2 == pytest.approx(expected, rel=1e-4)
    assert c.offset_v == 0.0


def _assert_moments_match(samples: np.ndarray, mean: float, variance: float, z: float = 5.0) -> None:
    """Sample mean and variance within z standard errors (variance SE from the sample fourth moment)."""
    n = samples.size
    centred = samples - samples.mean()
    sample_var = centred.var(ddof=1)
    mean_se = np.sqrt(variance / n)
    var_se = np.sqrt((np.mean(centred**4) - sample_var**2) / n)
    assert abs(samples.mean() - mean) < z * mean_se, (samples.mean(), mean, mean_se)
    assert abs(sample_var - variance) < z * var_se, (sample_var, variance, var_se)


@pytest.mark.parametrize("photons", [0.0, 30.0, 1000.0, 16765.0])
def test_sample_bin_voltage__mean_and_variance_match_eq21_28_29(photons):
    c = chain()
    draws = c.sample_bin_voltage(np.full(200_000, photons), np.random.default_rng(int(photons) + 1))
    _assert_moments_match(draws, float(c.bin_mean_voltage(photons)), float(c.bin_voltage_variance(photons)))


@pytest.mark.parametrize("photons", [0.0, 30.0, 16765.0])
def test_sample_bin_voltage__every_optional_noise_term_and_noise_scale(config, photons):
    simulator = {"noise_scale": 0.5, "background_mean_electrons": 20.0, "background_std_electrons": 3.0,
                 "tia_noise_mean_electrons": 100.0, "random_noise_std_v": 2e-3}
    sensor = config.sensor.model_copy(update={"dark_current_fom_a_per_m2": 100.0})
    c = DetectorChain.from_config(sensor, config.simulator.model_copy(update=simulator))
    assert c.dark_electrons > 0 and c.offset_v > 0
    draws = c.sample_bin_voltage(np.full(200_000, photons), np.random.default_rng(7))
    _assert_moments_match(draws, float(c.bin_mean_voltage(photons)), float(c.bin_voltage_variance(photons)))
    # the photon-dependent part is unchanged by the signal-free terms
    assert c.variance_per_photon_v2 == pytest.approx(0.25 * chain().variance_per_photon_v2, rel=1e-12)


def test_sample_bin_voltage__noiseless_is_the_mean():
    c = chain(noise_scale=0.0)
    photons = np.array([0.0, 3.0, 1e4])
    np.testing.assert_array_equal(c.sample_bin_voltage(photons, np.random.default_rng(0)),
                                  c.bin_mean_voltage(photons))
    assert c.bin_voltage_variance(1e4) == 0.0


def test_bin_photons__rounding_is_switchable():
    x = np.array([0.4, 0.6, 2.5, 16764.7])
    np.testing.assert_array_equal(chain(round_photons=True).bin_photons(x), [0.0, 1.0, 2.0, 16765.0])
    np.testing.assert_array_equal(chain(round_photons=False).bin_photons(x), x)


# --- noiseless simulation returns the truth -------------------------------------------------------------

DEPTHS = np.linspace(1.4, 2.4, 41)


def test_measure__noiseless_default_window_has_small_fixed_depth_bias(noiseless, scene, fidelity):
    sensor = make_sensor(noiseless(fidelity))
    depth, _ = sensor.measure(scene(DEPTHS, rho_sas=0.5), np.random.default_rng(0))
    error = depth - DEPTHS[:, None]
    assert np.abs(error).max() < 0.7e-3
    assert np.abs(error[:, 0]).min() > 0.1e-3  # 12.5 MHz: 2667 bins are not whole cycles
    assert np.abs(error[:, 3]).max() < 0.1e-3  # 31.25 MHz: ~0.04 mm at most
    # fixed: a property of the window and the phase alone, not of the signal level
    darker, _ = sensor.measure(scene(DEPTHS, rho_sas=0.05), np.random.default_rng(0))
    np.testing.assert_allclose(darker, depth, rtol=0, atol=1e-9)


def test_measure__noiseless_fidelities_agree(noiseless, scene):
    theta = scene(DEPTHS, d_ab=0.1, rho_sas=0.6, rho_sab=0.6, rho_aba=0.8, rho_bas=0.6)
    moment = make_sensor(noiseless("moment")).measure(theta, np.random.default_rng(0))
    waveform = make_sensor(noiseless("waveform")).measure(theta, np.random.default_rng(0))
    np.testing.assert_allclose(moment[0], waveform[0], rtol=0, atol=1e-9)
    np.testing.assert_allclose(moment[1], waveform[1], rtol=1e-9)


def test_measure__noiseless_whole_cycles_is_exact(noiseless, scene, fidelity):
    rho = np.linspace(0.05, 1.0, DEPTHS.size)
    depth, amplitude = make_sensor(noiseless(fidelity, whole_cycles=True)).measure(
        scene(DEPTHS, rho_sas=rho), np.random.default_rng(0))
    np.testing.assert_allclose(depth, DEPTHS[:, None] * np.ones(4), rtol=0, atol=1e-6)
    gamma_d = 0.1794 * rho / DEPTHS**2
    np.testing.assert_allclose(amplitude, gamma_d[:, None] * np.ones(4), rtol=1e-6)


def test_measure__noiseless_default_window_amplitude_is_gamma_d(noiseless, scene, fidelity):
    _, amplitude = make_sensor(noiseless(fidelity)).measure(scene(DEPTHS, rho_sas=0.5), np.random.default_rng(0))
    gamma_d = 0.1794 * 0.5 / DEPTHS**2
    np.testing.assert_allclose(amplitude, gamma_d[:, None] * np.ones(4), rtol=1e-3)


@pytest.mark.parametrize(("whole_cycles", "depth_atol", "amplitude_rtol"), [(True, 1e-6, 1e-6), (False, 0.7e-3, 1e-3)])
def test_measure__noiseless_multipath_amplitude_is_phasor_sum(noiseless, reciprocal_scene, fidelity, whole_cycles,
                                                            depth_atol, amplitude_rtol):
    d_ab = np.linspace(0.0, 0.15, DEPTHS.size)
    theta = reciprocal_scene(DEPTHS, rho=0.7, d_ab=d_ab, rho_aba=0.8)
    depth, amplitude = make_sensor(noiseless(fidelity, whole_cycles=whole_cycles)).measure(
        theta, np.random.default_rng(0))
    gamma_d, phi_d, gamma_m, phi_m = two_path_phasors(theta, FREQS, 0.1794, C)
    phasor = gamma_d * np.exp(1j * phi_d) + gamma_m * np.exp(1j * phi_m)
    np.testing.assert_allclose(amplitude, np.abs(phasor), rtol=amplitude_rtol)
    expected_depth = np.mod(np.angle(phasor), 2 * np.pi) * C / (4 * np.pi * FREQS)
    np.testing.assert_allclose(depth, expected_depth, rtol=0, atol=depth_atol)
    assert np.abs(expected_depth - DEPTHS[:, None]).max() > 5e-3  # the multipath really is there


WRAP_CASES = [2.4, 4.8 - 2e-3, 4.8 + 2e-3, 6.0 - 2e-3, 6.0 + 2e-3, 8.0 + 2e-3, 12.0 - 2e-3]


@pytest.mark.parametrize("whole_cycles", [False, True])
@pytest.mark.parametrize("d_as", WRAP_CASES)
def test_measure__noiseless_depth_near_phase_wrap_points(noiseless, scene, fidelity, d_as, whole_cycles):
    # d = 2.4 m at 31.25 MHz is exactly phi = pi: it must come back as 2.4 m, not -2.4 m or 0
    depth, _ = make_sensor(noiseless(fidelity, whole_cycles=whole_cycles)).measure(
        scene(d_as, rho_sas=1.0), np.random.default_rng(0))
    expected = np.mod(d_as, RANGES)
    np.testing.assert_allclose(depth[0], expected, rtol=0, atol=1e-6 if whole_cycles else 0.7e-3)
    assert np.all((depth >= 0) & (depth < RANGES))


def test_measure__noiseless_depth_matches_direct_bin_sum(noiseless, reciprocal_scene, fidelity):
    """Independent re-derivation of the calibration: x(t_i), V_i = g x_i, C_n = (m/K) sum V_i cos(...)."""
    theta = reciprocal_scene(np.array([1.4, 1.9, 2.4]), rho=np.array([1.0, 0.3, 0.14]),
                             d_ab=np.array([0.0, 0.05, 0.15]), rho_aba=np.array([0.0, 0.5, 1.0]))
    depth, amplitude = make_sensor(noiseless(fidelity)).measure(theta, np.random.default_rng(0))
    m, alpha, g, k = 0.4785, 1.0, 4.4727430920833e-5, 2667
    t = np.arange(k) * 6e-9
    for row, (d_as, d_ab, rho, _, rho_aba, _) in enumerate(theta):
        gamma_d, gamma_m = 0.1794 * rho / d_as**2, 0.1794 * rho**2 * rho_aba / d_as**2
        for j, f in enumerate(FREQS):
            w = 2 * np.pi * f
            phi_d, phi_m = 4 * np.pi * f * d_as / C, 4 * np.pi * f * (d_as + d_ab) / C
            x = (2 * gamma_d / (alpha * m) * (1 + alpha * np.cos(w * t - phi_d))
                 + 2 * gamma_m / (alpha * m) * (1 + alpha * np.cos(w * t - phi_m))) / g
            taps = [m / k * np.sum(g * x * np.cos(w * t + n * np.pi / 2)) for n in range(4)]
            phase = np.arctan2(taps[3] - taps[1], taps[0] - taps[2]) % (2 * np.pi)
            assert depth[row, j] == pytest.approx(C * phase / (4 * np.pi * f), abs=1e-9)
            assert amplitude[row, j] == pytest.approx(np.hypot(taps[3] - taps[1], taps[2] - taps[0]) / 2, rel=1e-8)


# --- noise level at the reference point -------------------------------------------------------------------


def _analytic_depth_std(sensor: MomentSensor, theta: np.ndarray) -> np.ndarray:
    """Depth std per frequency from the perpendicular std of (P, Q) over Gamma, times c / (4 pi f)."""
    mean, cov = sensor.quadrature_moments(theta, multipath=False)
    gamma = np.hypot(mean[..., 0], mean[..., 1])
    perpendicular = np.stack([-mean[..., 1], mean[..., 0]], -1) / gamma[..., None]
    perpendicular_var = np.einsum("...i,...ij,...j->...", perpendicular, cov, perpendicular)
    return np.sqrt(perpendicular_var) / gamma * C / (4 * np.pi * FREQS)


def test_quadrature_moments__depth_noise_std_1p16_mm_at_31p25_mhz(config, scene):
    std = _analytic_depth_std(MomentSensor(config), scene(1.4, rho_sas=0.5))[0]
    assert std[3] == pytest.approx(1.16e-3, abs=0.01e-3)
    # noise is dominated by the signal-free terms, so the depth std scales as 1/f
    np.testing.assert_allclose(std * FREQS, std[3] * FREQS[3], rtol=0.02)


@pytest.mark.parametrize(("fidelity_name", "n"), [("moment", 20_000), ("waveform", 1_000)])
def test_measure__simulated_depth_std_matches_analytic(config, scene, fidelity_name, n):
    theta = scene(np.full(n, 1.4), rho_sas=0.5)
    analytic = _analytic_depth_std(MomentSensor(config), theta[:1])[0, 3]
    depth, _ = make_sensor(config.replace(simulator={"fidelity": fidelity_name})).measure(
        theta, np.random.default_rng(11))
    sample_std = depth[:, 3].std(ddof=1)
    # (n - 1) s^2 / sigma^2 ~ chi^2(n - 1): accept the central 99.9 %
    low, high = stats.chi2.ppf([0.0005, 0.9995], n - 1)
    statistic = (n - 1) * sample_std**2 / analytic**2
    assert low < statistic < high, (sample_std, analytic)
    assert abs(depth[:, 3].mean() - 1.4) < 0.1e-3 + 5 * analytic / np.sqrt(n)


# --- the backend contract, one class for every fidelity ---------------------------------------------------


@pytest.mark.parametrize("fidelity_name", sorted(FIDELITIES))
class TestSensorModelContract:
    def sensor(self, fidelity_name: str, **simulator: object) -> SensorModel:
        return make_sensor(Config().replace(simulator={"fidelity": fidelity_name, **simulator}))

    def test_make_sensor__builds_the_configured_fidelity(self, fidelity_name):
        sensor = self.sensor(fidelity_name)
        assert isinstance(sensor, FIDELITIES[fidelity_name])
        assert isinstance(sensor, SensorModel)
        assert isinstance(sensor, MomentSensor if fidelity_name == "moment" else WaveformSensor)

    def test_taps__shape_dtype_and_parallel_phase_structure(self, fidelity_name, rng):
        theta = sample_theta(Config().prior, 9, rng)
        taps = self.sensor(fidelity_name).taps(theta, np.random.default_rng(1))
        assert taps.shape == (9, 4, 4) and taps.dtype == np.float64
        scale = np.abs(taps).max()
        np.testing.assert_allclose(taps[..., 2], -taps[..., 0], rtol=0, atol=1e-12 * scale)
        np.testing.assert_allclose(taps[..., 3], -taps[..., 1], rtol=0, atol=1e-12 * scale)

    def test_taps__single_scene_accepts_1d_theta(self, fidelity_name):
        theta = np.array([1.8, 0.05, 0.5, 0.5, 0.3, 0.5])
        one = self.sensor(fidelity_name).taps(theta, np.random.default_rng(4))
        two = self.sensor(fidelity_name).taps(theta[None, :], np.random.default_rng(4))
        assert one.shape == (1, 4, 4)
        np.testing.assert_array_equal(one, two)

    def test_taps__same_seed_is_bitwise_identical(self, fidelity_name, rng):
        theta = sample_theta(Config().prior, 260, rng)  # more than one waveform batch of 256 rows
        first = self.sensor(fidelity_name).taps(theta, np.random.default_rng(2026))
        second = self.sensor(fidelity_name).taps(theta, np.random.default_rng(2026))
        assert first.tobytes() == second.tobytes()
        other = self.sensor(fidelity_name).taps(theta[:20], np.random.default_rng(2027))
        assert not np.any(other == first[:20])

    def test_taps__noiseless_is_deterministic(self, fidelity_name, rng):
        theta = sample_theta(Config().prior, 5, rng)
        sensor = self.sensor(fidelity_name, noise_scale=0.0)
        a = sensor.taps(theta, np.random.default_rng(1))
        b = sensor.taps(theta, np.random.default_rng(2))
        np.testing.assert_array_equal(a, b)

    def test_taps__multipath_false_equals_zero_coupling(self, fidelity_name, rng):
        theta = sample_theta(Config().prior, 6, rng)
        no_coupling = theta.copy()
        no_coupling[:, 4] = 0.0
        sensor = self.sensor(fidelity_name)
        dropped = sensor.taps(theta, np.random.default_rng(5), multipath=False)
        np.testing.assert_array_equal(dropped, sensor.taps(no_coupling, np.random.default_rng(5)))
        assert not np.array_equal(dropped, sensor.taps(theta, np.random.default_rng(5)))

    def test_measure__depth_within_unambiguous_range(self, fidelity_name, rng):
        prior = Config().prior.model_copy(update={"d_as_m": (0.5, 13.0)})
        theta = sample_theta(prior, 200, rng)
        depth, amplitude = self.sensor(fidelity_name).measure(theta, np.random.default_rng(6))
        assert depth.shape == amplitude.shape == (200, 4)
        assert np.all((depth >= 0) & (depth <= RANGES))
        assert np.all(amplitude >= 0)
