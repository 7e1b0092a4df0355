"""Moment-matched simulator: exact tap moments, and agreement in distribution with the waveform simulator."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy import stats

from mpi_lidar.config import Config
from mpi_lidar.physics import demod, make_sensor
from mpi_lidar.physics.moments import MomentSensor
from mpi_lidar.simulation.sampling import sample_theta

# Below ~1000 photons per bin at the peak the rounding of eq 16 moves the phase by more than 1e-4 rad.
LOW_SIGNAL_PEAK_PHOTONS = 1000.0
# A prior wide enough to reach both high signals and low ones (peak < 1000 photons).
WIDE_PRIOR = Config().prior.model_copy(update={"albedo": (0.002, 1.0), "d_as_m": (0.5, 5.0)})


def _assert_taps_close(actual: np.ndarray, expected: np.ndarray, rel: float) -> None:
    """|actual - expected| <= rel * (largest |tap| of the same sample and frequency)."""
    scale = np.abs(expected).max(axis=-1, keepdims=True)
    worst = float((np.abs(actual - expected) / scale).max())
    assert worst <= rel, f"worst relative tap error {worst:.2e} > {rel:.0e}"


def _waveform_taps(config: Config, theta: np.ndarray) -> np.ndarray:
    return make_sensor(config.replace(simulator={"fidelity": "waveform"})).taps(theta, np.random.default_rng(0))


@pytest.mark.unit
@settings(max_examples=30, deadline=None, derandomize=True)
@given(seed=st.integers(0, 2**32 - 1), whole_cycles=st.booleans())
def test_tap_moments__covariance_is_symmetric_psd_rank_two(seed, whole_cycles):
    sensor = MomentSensor(Config().replace(simulator={"whole_cycles": whole_cycles}))
    theta = sample_theta(WIDE_PRIOR, 16, np.random.default_rng(seed))
    mean, cov = sensor.tap_moments(theta)
    assert mean.shape == (16, 4, 4) and cov.shape == (16, 4, 4, 4)
    scale = np.abs(cov).max(axis=(-2, -1), keepdims=True)
    np.testing.assert_allclose(cov, np.swapaxes(cov, -1, -2), rtol=0, atol=1e-14 * scale.max())
    eigenvalues = np.linalg.eigvalsh(cov)  # ascending
    largest = eigenvalues[..., -1:]
    assert np.all(np.abs(eigenvalues[..., :2]) <= 1e-12 * largest)  # rank 2 ...
    assert np.all(eigenvalues[..., 2:] > 1e-6 * largest)  # ... and positive definite on the (P, Q) plane
    # parallel phase: C2 = -C0 and C3 = -C1 in the mean and in the covariance
    np.testing.assert_array_equal(mean[..., 2], -mean[..., 0])
    np.testing.assert_array_equal(mean[..., 3], -mean[..., 1])
    np.testing.assert_allclose(cov[..., 2, :], -cov[..., 0, :], rtol=0, atol=1e-14 * scale.max())
    np.testing.assert_allclose(cov[..., 3, :], -cov[..., 1, :], rtol=0, atol=1e-14 * scale.max())


@pytest.mark.unit
@pytest.mark.parametrize("whole_cycles", [False, True])
def test_tap_moments__mean_equals_noiseless_waveform_taps(noiseless, whole_cycles):
    config = noiseless("moment", whole_cycles=whole_cycles)
    theta = sample_theta(WIDE_PRIOR, 40, np.random.default_rng(8))
    mean, _ = MomentSensor(config).tap_moments(theta)
    expected = _waveform_taps(config, theta)
    _assert_taps_close(mean, expected, rel=1e-9)


@pytest.mark.unit
def test_tap_moments__mean_does_not_depend_on_noise_scale(reciprocal_scene):
    theta = reciprocal_scene(np.array([1.4, 2.4]), rho=np.array([1.0, 0.01]), d_ab=0.1, rho_aba=0.8)
    noisy, _ = MomentSensor(Config()).tap_moments(theta)
    quiet, quiet_cov = MomentSensor(Config().replace(simulator={"noise_scale": 0.0})).tap_moments(theta)
    np.testing.assert_array_equal(noisy, quiet)
    np.testing.assert_array_equal(quiet_cov, 0.0)


@pytest.mark.unit
@pytest.mark.parametrize("rho", [0.002, 0.005, 0.02, 0.11])
def test_tap_moments__binwise_mean_equals_rounded_noiseless_waveform(reciprocal_scene, rho):
    # a low peak photon count, where the rounding of eq 16 matters
    theta = reciprocal_scene(2.0, rho=rho, d_ab=0.07, rho_aba=0.6)
    config = Config()
    sensor = MomentSensor(config)
    assert sensor.photon_waveforms(theta)[0].peak[0] < LOW_SIGNAL_PEAK_PHOTONS
    mean, _ = sensor.tap_moments(theta)
    rounded = _waveform_taps(config.replace(simulator={"noise_scale": 0.0}), theta)
    _assert_taps_close(mean, rounded, rel=1e-9)
    scale = np.abs(rounded).max()
    # the rounding is not a no-op here: without it the taps differ by far more than the tolerance
    unrounded = _waveform_taps(config.replace(simulator={"noise_scale": 0.0, "round_photons": False}), theta)
    assert np.abs(unrounded - rounded).max() > 1e-6 * scale


@pytest.mark.unit
@pytest.mark.parametrize("whole_cycles", [False, True])
@pytest.mark.parametrize("peak_photons", [1001.0, 2000.0, 16765.0, 33000.0])
def test_tap_moments__rounded_mean_equals_rounded_noiseless_waveform_at_any_signal(scene, peak_photons,
                                                                                   whole_cycles):
    # The rounding errors of eq 16 repeat with the bin phases every few bins, so they add up coherently over
    # the window (~0.5 / peak rad, 0.3 mm at 12.5 MHz for a 2000-photon peak): ignoring them is not exact.
    d_as = np.linspace(1.4, 2.4, 21)
    config = Config().replace(simulator={"whole_cycles": whole_cycles})
    theta = scene(d_as, rho_sas=peak_photons / (2 * 16764.729) * d_as**2)
    mean, _ = MomentSensor(config).tap_moments(theta)
    rounded = _waveform_taps(config.replace(simulator={"noise_scale": 0.0}), theta)
    _assert_taps_close(mean, rounded, rel=1e-9)


@pytest.mark.unit
@pytest.mark.parametrize(("rho", "round_photons"), [(1.0, False), (0.14, False), (1.0, True), (0.005, True)])
def test_quadrature_moments__covariance_equals_direct_bin_sum(reciprocal_scene, rho, round_photons):
    """Independent method: Cov(C_n, C_k) = (m/K)^2 sum_i Var(V_i) cos(w t_i + n pi/2) cos(w t_i + k pi/2)."""
    config = Config().replace(simulator={"round_photons": round_photons})
    sensor = MomentSensor(config)
    theta = reciprocal_scene(2.1, rho=rho, d_ab=0.12, rho_aba=0.9)
    _, cov = sensor.tap_moments(theta)
    m = config.sensor.demodulation_amplitude_v
    for j, waveform in enumerate(sensor.photon_waveforms(theta)):
        wt = sensor.phases(j)
        photons = sensor.chain.bin_photons(waveform.at(wt))[0]  # rounded when configured
        variance = sensor.chain.bin_voltage_variance(photons)
        weights = m / wt.size * np.cos(wt[:, None] + demod.TAP_SHIFTS_RAD[None, :])
        expected = weights.T @ (variance[:, None] * weights)
        np.testing.assert_allclose(cov[0, j], expected, rtol=0, atol=1e-9 * np.abs(expected).max())


@pytest.mark.unit
def test_taps__gaussian_samples_have_the_tap_moments(reciprocal_scene):
    sensor = MomentSensor(Config())
    n = 20_000
    theta = reciprocal_scene(np.full(n, 1.9), rho=0.4, d_ab=0.1, rho_aba=0.8)
    taps = sensor.taps(theta, np.random.default_rng(99))
    mean, cov = sensor.tap_moments(theta[:1])
    for j in range(4):
        pq = taps[:, j, [0, 3]]
        target_mean, target_cov = mean[0, j, [0, 3]], cov[0, j][np.ix_([0, 3], [0, 3])]
        se = np.sqrt(np.diag(target_cov) / n)
        assert np.all(np.abs(pq.mean(0) - target_mean) < 5 * se)
        # sample covariance of a Gaussian: Var(S_ab) = (S_aa S_bb + S_ab^2) / n
        sample_cov = np.cov(pq.T)
        cov_se = np.sqrt((np.outer(np.diag(target_cov), np.diag(target_cov)) + target_cov**2) / n)
        assert np.all(np.abs(sample_cov - target_cov) < 5 * cov_se)


# --- moment and waveform simulators agree in distribution ----------------------------------------------------

OPERATING_POINTS = {
    # name: (d_AS [m], rho_SAS = rho_SAB = rho_BAS, d_AB [m], rho_ABA); the last two give the multipath.
    # The low signal is taken with its multipath only: that point holds the direct path of the same signal too
    # (about 900 photons a bin) and takes the same code path (rounding on, bin-wise moments).
    "high_signal": (1.4, 1.0, 0.0, 0.0),
    "high_signal_multipath": (1.4, 1.0, 0.1, 0.8),
    "low_signal_multipath": (2.4, 0.14, 0.1, 0.8),  # ~400 photons/bin of the direct path: bin-wise moments
    "few_photons": (2.4, 0.005, 0.0, 0.0),  # ~15 photons/bin: rounding of eq 16 matters
}
WAVEFORM_SAMPLES = 1500
KS_FAMILY_ALPHA = 0.01
Z_LIMIT = 4.0


def _variance_se(x: np.ndarray) -> float:
    centred = x - x.mean()
    return float(np.sqrt((np.mean(centred**4) - centred.var() ** 2) / x.size))


@pytest.mark.integration
@pytest.mark.slow
@pytest.mark.parametrize("point", sorted(OPERATING_POINTS))
def test_measure__moment_and_waveform_agree_in_distribution(reciprocal_scene, point):
    d_as, rho, d_ab, rho_aba = OPERATING_POINTS[point]
    config = Config()
    moment = make_sensor(config)
    waveform = make_sensor(config.replace(simulator={"fidelity": "waveform"}))
    moment_samples = 20_000
    m_depth, m_amp = moment.measure(reciprocal_scene(np.full(moment_samples, d_as), rho, d_ab, rho_aba),
                                    np.random.default_rng(1))
    w_depth, w_amp = waveform.measure(reciprocal_scene(np.full(WAVEFORM_SAMPLES, d_as), rho, d_ab, rho_aba),
                                      np.random.default_rng(2))
    comparisons = [(f"{kind} {f / 1e6:g} MHz", m[:, j], w[:, j])
                   for kind, m, w in (("depth", m_depth, w_depth), ("amplitude", m_amp, w_amp))
                   for j, f in enumerate(config.frequencies_hz)]
    threshold = KS_FAMILY_ALPHA / len(comparisons)  # Bonferroni
    for label, a, b in comparisons:
        p_value = stats.ks_2samp(a, b).pvalue
        assert p_value > threshold, f"{point} {label}: KS p = {p_value:.2e}"
        mean_se = np.sqrt(a.var() / a.size + b.var() / b.size)
        assert abs(a.mean() - b.mean()) < Z_LIMIT * mean_se, f"{point} {label}: means differ"
        var_se = np.hypot(_variance_se(a), _variance_se(b))
        assert abs(a.var() - b.var()) < Z_LIMIT * var_se, f"{point} {label}: variances differ"
