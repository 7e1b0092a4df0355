"""Two-path inverse solvers: exact recovery on closed-form phasors, degenerate cases, status codes."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.optimize import least_squares

from mpi_lidar.config import PAPER_FREQUENCIES_HZ, Config
from mpi_lidar.errors import MpiLidarError
from mpi_lidar.physics import inverse
from mpi_lidar.physics.inverse import (
    FIT_OK,
    NOT_FINITE,
    OUT_OF_BOUNDS,
    SINGLE_PATH,
    least_squares_two_path,
    model_phasors,
    prony_two_path,
)
from mpi_lidar.physics.moments import MomentSensor
from mpi_lidar.physics.transport import path_phasor, two_path_phase_bias, two_path_phasors

FREQS = np.array(PAPER_FREQUENCIES_HZ)
C = 3.0e8
GAMMA_R = Config().sensor.gamma_r_v2


def closed_form_raw(theta: np.ndarray, freqs: np.ndarray = FREQS) -> np.ndarray:
    """Noiseless depth and amplitude (n, 2F) of the two-path phasor sum, eq 11-15 and eq 5-7."""
    gamma_d, phi_d, gamma_m, phi_m = two_path_phasors(theta, freqs, GAMMA_R, C)
    z = gamma_d * np.exp(1j * phi_d) + gamma_m * np.exp(1j * phi_m)
    depth = np.mod(np.angle(z), 2 * np.pi) * C / (4 * np.pi * freqs)
    return np.hstack([depth, np.abs(z)])


def reciprocal(d_as, d_ab, albedo, coupling) -> np.ndarray:
    d_as, d_ab, albedo, coupling = np.broadcast_arrays(*(np.atleast_1d(np.asarray(x, float))
                                                         for x in (d_as, d_ab, albedo, coupling)))
    return np.column_stack([d_as, d_ab, albedo, albedo, coupling, albedo])


def random_two_path(n: int, seed: int, d_ab=(0.01, 0.15), coupling=(0.1, 1.0)) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return reciprocal(rng.uniform(1.4, 2.4, n), rng.uniform(*d_ab, n), rng.uniform(0.3, 1.0, n),
                      rng.uniform(*coupling, n))


def single_path_bias_bound(theta: np.ndarray) -> np.ndarray:
    """Largest depth bias that the multipath adds at any frequency (closed form of eq 11). [m]"""
    ratio = theta[:, 3] * theta[:, 4] * theta[:, 5] / theta[:, 2]
    w = 4 * np.pi * FREQS[None, :] / C
    return (np.abs(two_path_phase_bias(ratio[:, None], w * theta[:, 1:2])) / w).max(axis=1)


@pytest.mark.unit
def test_prony_two_path__exact_on_noiseless_phasors():
    theta = random_two_path(400, seed=1)
    fit = prony_two_path(closed_form_raw(theta), FREQS)
    assert np.all(fit.status == FIT_OK)
    # the poles lie within 0.04 rad: the fit amplifies rounding errors of the input ~1e8 times
    np.testing.assert_allclose(fit.direct_depth_m, theta[:, 0], rtol=0, atol=1e-6)
    np.testing.assert_allclose(fit.path_offset_m, theta[:, 1], rtol=0, atol=1e-5)
    gamma_d = GAMMA_R * theta[:, 2] / theta[:, 0] ** 2
    gamma_m = GAMMA_R * theta[:, 3] * theta[:, 4] * theta[:, 5] / theta[:, 0] ** 2
    np.testing.assert_allclose(fit.direct_amplitude, gamma_d, rtol=1e-5)
    np.testing.assert_allclose(fit.multipath_amplitude, gamma_m, rtol=1e-4)
    assert fit.cost.max() < 1e-16


@pytest.mark.unit
def test_least_squares_two_path__exact_on_noiseless_phasors():
    theta = random_two_path(80, seed=2)
    fit = least_squares_two_path(closed_form_raw(theta), FREQS)
    assert np.all(fit.status == FIT_OK)
    np.testing.assert_allclose(fit.direct_depth_m, theta[:, 0], rtol=0, atol=1e-6)
    np.testing.assert_allclose(fit.path_offset_m, theta[:, 1], rtol=0, atol=1e-5)
    assert fit.cost.max() < 1e-16


@pytest.mark.unit
def test_least_squares_two_path__flat_valley_from_single_path_start():
    # Without Prony's start the fit matches the phasors to 1e-6 while d_AS is still millimetres off: the
    # two-path problem is that ill-conditioned, which is why the solvers lose to raw depth under noise.
    theta = random_two_path(30, seed=2)
    raw = closed_form_raw(theta)
    no_start = prony_two_path(raw * np.r_[np.ones(4), np.zeros(4)], FREQS)
    assert np.all(no_start.status == NOT_FINITE)
    fit = least_squares_two_path(raw, FREQS, start=no_start)
    assert np.all(np.isfinite(fit.direct_depth_m))
    assert np.median(fit.cost) < 1e-10
    assert np.abs(fit.direct_depth_m - theta[:, 0]).max() > 1e-4


@pytest.mark.unit
def test_measured_phasors__follow_the_transport_sign_convention():
    """z_k = A_k exp(+i 4 pi f_k d_k / c): the phasor of the forward model (transport.path_phasor), whose angle
    is the demodulated phase."""
    theta = random_two_path(20, seed=4)
    raw = closed_form_raw(theta)
    gamma_d, phi_d, gamma_m, phi_m = two_path_phasors(theta, FREQS, GAMMA_R, C)
    z = inverse.measured_phasors(raw, FREQS)
    np.testing.assert_allclose(z, gamma_d * np.exp(1j * phi_d) + gamma_m * np.exp(1j * phi_m), rtol=1e-12)
    np.testing.assert_array_equal(z, path_phasor(raw[:, 4:], raw[:, :4], FREQS, C))
    # +phi, not -phi: at 12.5 MHz phi_d is 0.7-1.3 rad and the multipath moves it by less than 0.2 rad
    assert np.all(np.abs(np.angle(z[:, 0]) - phi_d[:, 0]) < 0.2)


@pytest.mark.unit
def test_model_phasors__reproduce_measured_phasors():
    theta = random_two_path(50, seed=3)
    raw = closed_form_raw(theta)
    ratio = theta[:, 3] * theta[:, 4] * theta[:, 5] / theta[:, 2]
    gamma_d = GAMMA_R * theta[:, 2] / theta[:, 0] ** 2
    model = model_phasors(theta[:, 0], theta[:, 1], gamma_d, ratio * gamma_d, FREQS)
    np.testing.assert_allclose(model, inverse.measured_phasors(raw, FREQS), rtol=1e-12, atol=1e-15)


@pytest.mark.unit
@pytest.mark.parametrize("solver", [prony_two_path, least_squares_two_path])
def test_two_path_solvers__no_multipath_is_single_path_with_exact_depth(solver):
    theta = reciprocal(np.linspace(1.4, 2.4, 11), 0.1, 0.6, 0.0)  # Gamma_M = 0: one pole
    fit = solver(closed_form_raw(theta), FREQS)
    assert np.all(fit.status == SINGLE_PATH)
    np.testing.assert_allclose(fit.direct_depth_m, theta[:, 0], rtol=0, atol=1e-9)
    assert np.all(fit.path_offset_m == 0) and np.all(fit.multipath_amplitude == 0)


@pytest.mark.unit
@pytest.mark.parametrize("solver", [prony_two_path, least_squares_two_path])
def test_two_path_solvers__zero_offset_merges_poles_into_single_path(solver):
    theta = reciprocal(np.linspace(1.4, 2.4, 11), 0.0, 0.8, 0.7)  # d_AB = 0: the two poles coincide
    fit = solver(closed_form_raw(theta), FREQS)
    assert np.all(fit.status == SINGLE_PATH)
    np.testing.assert_allclose(fit.direct_depth_m, theta[:, 0], rtol=0, atol=1e-9)
    # the single path carries both amplitudes
    np.testing.assert_allclose(fit.direct_amplitude, GAMMA_R * (0.8 + 0.8**2 * 0.7) / theta[:, 0] ** 2,
                               rtol=1e-9)


@pytest.mark.unit
def test_prony_two_path__near_merged_poles_error_within_single_path_bias():
    d_ab = np.geomspace(1e-9, 2e-2, 60)
    theta = reciprocal(1.9, d_ab, 0.9, 0.9)
    fit = prony_two_path(closed_form_raw(theta), FREQS)
    assert set(np.unique(fit.status)) <= {FIT_OK, SINGLE_PATH, OUT_OF_BOUNDS}
    assert np.any(fit.status == SINGLE_PATH) and np.any(fit.status == FIT_OK)
    error = np.abs(fit.direct_depth_m - theta[:, 0])
    assert np.all(error <= single_path_bias_bound(theta) + 1e-7)


@pytest.mark.unit
def test_prony_two_path__depth_beyond_highest_frequency_range_is_unwrapped():
    # 31.25 MHz wraps at 4.8 m, 12.5 MHz at 12 m; the 6.25 MHz step is unambiguous to 24 m
    theta = reciprocal([2.4, 4.79, 4.81, 7.3, 11.9], 0.08, 0.9, 0.8)
    raw = closed_form_raw(theta)
    assert raw[2, 3] < 0.05  # the measured 31.25 MHz depth of 4.81 m has wrapped
    fit = prony_two_path(raw, FREQS)
    assert np.all(fit.status == FIT_OK)
    np.testing.assert_allclose(fit.direct_depth_m, theta[:, 0], rtol=0, atol=1e-6)


@pytest.mark.unit
def test_two_path_solvers__non_finite_rows_flagged_and_finite():
    raw = closed_form_raw(random_two_path(4, seed=4))
    raw[0, 2] = np.nan
    raw[1, 5] = np.inf
    raw[2, 6] = 0.0  # no return at one frequency
    for solver in (prony_two_path, least_squares_two_path):
        fit = solver(raw, FREQS)
        np.testing.assert_array_equal(fit.status[:3], NOT_FINITE)
        assert fit.status[3] == FIT_OK
        for field in ("direct_depth_m", "path_offset_m", "direct_amplitude", "multipath_amplitude", "cost"):
            assert np.all(np.isfinite(getattr(fit, field))), field


@pytest.mark.unit
def test_prony_two_path__rejects_unequally_spaced_frequencies():
    with pytest.raises(MpiLidarError, match="equally spaced"):
        prony_two_path(np.ones((1, 8)), [10e6, 12.5e6, 25e6, 31.25e6])
    with pytest.raises(MpiLidarError, match="at least 4"):
        prony_two_path(np.ones((1, 6)), [10e6, 20e6, 30e6])


def _noisy_raw(n: int, noise_scale: float, seed: int) -> tuple[np.ndarray, np.ndarray]:
    theta = random_two_path(n, seed, coupling=(0.0, 1.0), d_ab=(0.0, 0.15))
    sensor = MomentSensor(Config().replace(simulator={"noise_scale": noise_scale}))
    depth, amplitude = sensor.measure(theta, np.random.default_rng(seed))
    return theta, np.hstack([depth, amplitude])


@pytest.mark.unit
def test_least_squares_two_path__respects_bounds_and_stays_finite_under_noise():
    theta, raw = _noisy_raw(150, 1.0, seed=5)
    fit = least_squares_two_path(raw, FREQS, max_offset_m=0.15, max_ratio=1.0)
    assert np.all(np.isfinite(fit.direct_depth_m))
    assert np.all((fit.path_offset_m >= 0) & (fit.path_offset_m <= 0.15))
    assert np.all(fit.multipath_amplitude <= fit.direct_amplitude * (1 + 1e-12))
    assert set(np.unique(fit.status)) <= {FIT_OK, SINGLE_PATH, OUT_OF_BOUNDS}
    # a bad fit costs at most the fallback's depth: the worst error stays within the prior's multipath bias
    assert np.abs(fit.direct_depth_m - theta[:, 0]).max() < 0.1


@pytest.mark.integration
@pytest.mark.slow
def test_least_squares_two_path__cost_no_worse_than_scipy_trust_region():
    _, raw = _noisy_raw(6, 0.1, seed=6)
    fit = least_squares_two_path(raw, FREQS)
    z = inverse.measured_phasors(raw, FREQS)
    w = 4 * np.pi * FREQS / C
    for i in np.flatnonzero(fit.status != OUT_OF_BOUNDS):
        scale = np.abs(z[i]).mean()

        def residual(p, i=i, scale=scale):
            m = np.exp(1j * w * p[0]) * p[2] * (1 + p[3] * np.exp(1j * w * p[1]))
            r = (m - z[i]) / scale
            return np.concatenate([r.real, r.imag])

        best = np.inf
        for p0 in ([raw[i, 3], 0.03, raw[i, 7], 0.3], [raw[i, 3] - 0.01, 0.1, raw[i, 7], 0.6]):
            ref = least_squares(residual, p0, bounds=([-np.inf, 0, 0, 0], [np.inf, 0.15, np.inf, 1.0]),
                                xtol=1e-15, ftol=1e-15, gtol=1e-15)
            best = min(best, 2 * ref.cost)
        # within 1e-4 of the optimum's cost: far below what the noise moves it by (one sigma ~ 1 / 8)
        assert fit.cost[i] <= best * (1 + 1e-4) + 1e-18, (i, fit.cost[i], best)
