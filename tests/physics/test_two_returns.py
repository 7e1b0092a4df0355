"""Two returns in one footprint: the least-squares fit for any frequency set, checked against the closed form on
evenly spaced frequencies and against the truth and its Cramer-Rao bound on an uneven set."""

from __future__ import annotations

import numpy as np
import pytest

from mpi_lidar.config import Config
from mpi_lidar.physics.two_returns import (
    closed_form_two_returns,
    evenly_spaced,
    fit_two_returns,
    gap_ambiguity_m,
    least_squares_two_returns,
)

pytestmark = pytest.mark.unit

C = Config().sensor.speed_of_light_m_per_s
EVEN = np.asarray(Config().frequencies_hz)  # 12.5-31.25 MHz in steps of 6.25
UNEVEN = np.array([10e6, 20e6, 25e6, 40e6])
SIGMA_V2 = 2e-4  # the phasors' quadrature noise [V^2]


def _rows(freqs, near, far, a_near, a_far, rng=None):
    """Raw rows (n, 2F) of two returns, with quadrature noise of SIGMA_V2 where ``rng`` is given."""
    w = 4 * np.pi * freqs / C
    z = a_near[:, None] * np.exp(1j * w * near[:, None]) + a_far[:, None] * np.exp(1j * w * far[:, None])
    if rng is not None:
        z = z + SIGMA_V2 * (rng.standard_normal(z.shape) + 1j * rng.standard_normal(z.shape))
    return np.concatenate([np.mod(np.angle(z), 2 * np.pi) / w, np.abs(z)], axis=1)


def _truth(n, rng):
    near = rng.uniform(1.0, 5.0, n)
    return near, near + rng.uniform(3.0, 8.0, n), rng.uniform(0.006, 0.02, n), rng.uniform(0.006, 0.02, n)


def _crb_m(freqs, near, far, a_near, a_far):
    """The Cramer-Rao bound [m] of each range (n, 2) under quadrature noise SIGMA_V2, amplitudes unknown."""
    w = 4 * np.pi * freqs / C
    out = np.empty((near.size, 2))
    for i in range(near.size):
        e1, e2 = np.exp(1j * w * near[i]), np.exp(1j * w * far[i])
        cols = [1j * w * a_near[i] * e1, 1j * w * a_far[i] * e2, e1, e2]
        jac = np.stack([np.concatenate([c.real, c.imag]) / SIGMA_V2 for c in cols], axis=1)
        out[i] = np.sqrt(np.diag(np.linalg.inv(jac.T @ jac))[:2])
    return out


def test_least_squares_two_returns__the_closed_form_s_fit_on_evenly_spaced_frequencies():
    rng = np.random.default_rng(3)
    near, far, a_near, a_far = _truth(60, rng)
    rows = _rows(EVEN, near, far, a_near, a_far, rng)
    sigma = np.full((near.size, EVEN.size), SIGMA_V2)
    closed = closed_form_two_returns(rows, EVEN, sigma, C, (near + far) / 2)
    fitted = least_squares_two_returns(rows, EVEN, sigma, C, (near + far) / 2)
    # both reach the weighted least-squares minimum: the same ranges, never a worse residual
    same = np.abs(fitted.near_m - closed.near_m) < 1e-6
    assert same.mean() >= 0.95
    np.testing.assert_allclose(fitted.far_m[same], closed.far_m[same], atol=1e-6)
    np.testing.assert_allclose(fitted.chi2[same], closed.chi2[same], rtol=1e-6, atol=1e-9)
    assert np.all(fitted.chi2 <= closed.chi2 * (1 + 1e-6) + 1e-9)


def test_least_squares_two_returns__an_uneven_set_recovers_the_truth_within_its_cramer_rao_bound():
    rng = np.random.default_rng(5)
    near, far, a_near, a_far = _truth(80, rng)
    sigma = np.full((near.size, UNEVEN.size), SIGMA_V2)
    exact = least_squares_two_returns(_rows(UNEVEN, near, far, a_near, a_far), UNEVEN, sigma, C, (near + far) / 2)
    np.testing.assert_allclose(exact.near_m, near, atol=1e-6)
    np.testing.assert_allclose(exact.far_m, far, atol=1e-6)
    np.testing.assert_allclose(exact.far_amplitude, a_far, rtol=1e-6)
    noisy = least_squares_two_returns(_rows(UNEVEN, near, far, a_near, a_far, rng), UNEVEN, sigma, C,
                                      (near + far) / 2)
    errors = np.abs(np.column_stack([noisy.near_m - near, noisy.far_m - far]))
    ratio = errors / _crb_m(UNEVEN, near, far, a_near, a_far)
    # |N(0, 1)| has median 0.67: an efficient fit's error over its bound has about that median
    assert 0.4 < np.median(ratio) < 1.0 and np.mean(ratio < 3) > 0.97
    assert np.median(noisy.chi2) < 2 * 4  # chi^2(2F - 4) has mean 4


def test_fit_two_returns__the_closed_form_where_evenly_spaced_least_squares_elsewhere():
    near, far, a_near, a_far = np.array([1.7]), np.array([6.3]), np.array([0.02]), np.array([0.005])
    sigma = np.full((1, 4), 1e-4)
    for freqs in (EVEN, UNEVEN):
        fit = fit_two_returns(_rows(freqs, near, far, a_near, a_far), freqs, sigma, C)
        np.testing.assert_allclose([fit.near_m[0], fit.far_m[0], fit.weaker_share[0]], [1.7, 6.3, 0.2], atol=1e-6)
    assert evenly_spaced(EVEN) and not evenly_spaced(UNEVEN)


def test_gap_ambiguity_m__the_step_of_an_even_set_the_common_divisor_of_another():
    assert gap_ambiguity_m(EVEN, C) == pytest.approx(C / (2 * 6.25e6))
    assert gap_ambiguity_m(UNEVEN, C) == pytest.approx(C / (2 * 5e6))
