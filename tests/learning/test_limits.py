"""Bayes limit: the importance sampler against brute force, high-SNR recovery, and the estimator's optimality."""

from __future__ import annotations

import itertools

import numpy as np
import pytest
from scipy import integrate

from mpi_lidar.config import Config
from mpi_lidar.errors import MpiLidarError
from mpi_lidar.learning.limits import (
    _Posterior,
    _sample_coupling,
    bayes_limit,
    log_coupling_density,
    posterior_estimates,
    weighted_median,
)
from mpi_lidar.physics.moments import MomentSensor
from mpi_lidar.simulation.sampling import sample_theta


@pytest.mark.parametrize("albedo, coupling", [((0.14, 1.0), (0.0, 1.0)), ((0.3, 0.6), (0.2, 0.9))])
def test_log_coupling_density__integrates_to_one_and_matches_samples(albedo, coupling):
    prior = Config().prior.model_copy(update={"albedo": albedo, "coupling": coupling})
    upper = albedo[1] * coupling[1]
    total, _ = integrate.quad(lambda q: np.exp(log_coupling_density(np.array([q]), prior))[0], 0, upper,
                              points=[albedo[0] * coupling[1], albedo[1] * coupling[0]], limit=200)
    assert total == pytest.approx(1.0, abs=1e-6)
    samples = _sample_coupling(prior, (200_000,), np.random.default_rng(0))
    edges = np.linspace(0, upper, 21)
    counts, _ = np.histogram(samples, edges)
    expected = np.array([integrate.quad(lambda q: np.exp(log_coupling_density(np.array([q]), prior))[0], a, b)[0]
                         for a, b in itertools.pairwise(edges)]) * samples.size
    # Poisson counts: 5 sigma
    assert np.all(np.abs(counts - expected) <= 5 * np.sqrt(expected) + 1)
    assert np.all(np.isneginf(log_coupling_density(np.array([-0.1, upper + 0.01]), prior)))


def test_weighted_median__equal_weights_equal_numpy_median_and_weights_act_as_repeats():
    rng = np.random.default_rng(1)
    for m in (7, 8):
        x = rng.normal(size=(5, m))
        np.testing.assert_allclose(weighted_median(x, np.full((5, m), 1 / m)), np.median(x, axis=1), rtol=0,
                                   atol=1e-15)
    x = np.array([[0.0, 1.0, 10.0]])
    # weight 3/4 on the middle value: the median is that value
    assert weighted_median(x, np.array([[0.125, 0.75, 0.125]]))[0] == pytest.approx(1.0)


def _brute_force(raw: np.ndarray, config: Config, pool: int, seed: int):
    """Posterior of d_AS by self-normalised importance sampling from the full prior (sample_theta)."""
    theta = sample_theta(config.prior, pool, np.random.default_rng(seed))
    log_l = _Posterior(config).log_likelihood(theta[None], *_quadratures(raw, config))
    w = np.exp(log_l - log_l.max(axis=1, keepdims=True))
    w /= w.sum(axis=1, keepdims=True)
    x = np.ascontiguousarray(np.broadcast_to(theta[:, 0], w.shape))
    mean = (w * x).sum(axis=1)
    std = np.sqrt((w * (x - mean[:, None]) ** 2).sum(axis=1))
    return mean, weighted_median(x, w), std, 1 / (w**2).sum(axis=1)


def _quadratures(raw: np.ndarray, config: Config):
    z, _, _ = _Posterior(config).measured(raw)
    return z.real[:, None, :], z.imag[:, None, :]


@pytest.mark.slow
@pytest.mark.parametrize("no_multipath_fraction", [0.0, 0.5])
def test_posterior_estimates__agree_with_brute_force_prior_sampling(no_multipath_fraction):
    # A narrow prior in d_AS and albedo, so that sampling the prior itself reaches a usable sample size;
    # d_AB and rho_ABA keep their full ranges (the product density of rho_ABA is checked on the way), and
    # a share of rows without multipath puts a point mass at rho_ABA = 0.
    config = Config().replace(prior={"d_as_m": (1.9, 1.95), "albedo": (0.5, 0.55),
                                     "no_multipath_fraction": no_multipath_fraction})
    rng = np.random.default_rng(3)
    theta = sample_theta(config.prior, 4, rng)
    depth, amplitude = MomentSensor(config).measure(theta, rng)
    raw = np.hstack([depth, amplitude])
    bf_mean, bf_median, bf_std, bf_ess = _brute_force(raw, config, 120_000, seed=9)
    assert np.all(bf_ess > 40)
    est = posterior_estimates(raw, config, np.random.default_rng(4), pool=3000)
    assert np.all(est.ess > 300)
    se = np.sqrt(bf_std**2 / bf_ess + est.std_m**2 / est.ess)
    assert np.all(np.abs(est.mean_m - bf_mean) <= 4 * se)
    assert np.all(np.abs(est.median_m - bf_median) <= 5 * se)
    np.testing.assert_allclose(est.std_m, bf_std, rtol=0.25)


@pytest.mark.parametrize("round_photons, tolerance_m", [(False, 5e-5), (True, 1.5e-4)])
def test_bayes_limit__high_snr_posterior_median_is_the_truth(round_photons, tolerance_m):
    # multipath bias below 0.05 mm (d_AB <= 5 mm, Gamma_M / Gamma_D <= 0.01) and depth noise ~0.02 mm
    config = Config().replace(prior={"d_ab_m": (0.0, 0.005), "coupling": (0.0, 0.01)},
                              simulator={"noise_scale": 0.01, "round_photons": round_photons})
    result = bayes_limit(config, 20, np.random.default_rng(1), pool=300)
    assert np.abs(result.posterior_median_m - result.theta[:, 0]).max() < tolerance_m
    assert np.abs(result.posterior_mean_m - result.theta[:, 0]).max() < tolerance_m
    assert result.median_ess > 20


def test_bayes_limit__beats_raw_depth_at_table_i_noise():
    result = bayes_limit(Config(), 60, np.random.default_rng(2), pool=300)
    raw_error = result.raw[:, 3] - result.theta[:, 0]
    assert np.all(np.isfinite(result.posterior_median_m)) and np.all(np.isfinite(result.posterior_mean_m))
    assert result.mae_m < 0.7 * result.raw_mae_m
    assert result.rmse_m < 0.7 * np.sqrt((raw_error**2).mean())
    # the median minimises absolute error, the mean squared error (up to sampling noise of 60 rows)
    assert result.mae_m <= np.abs(result.posterior_mean_m - result.theta[:, 0]).mean() * 1.05
    assert result.median_ess > 100
    assert 0 < result.mae_se_m < result.mae_m


def test_bayes_limit__rejects_unsupported_configurations():
    with pytest.raises(MpiLidarError, match="reciprocal"):
        bayes_limit(Config().replace(prior={"scheme": "independent"}), 10, np.random.default_rng(0))
    with pytest.raises(MpiLidarError, match="noise_scale"):
        bayes_limit(Config().replace(simulator={"noise_scale": 0.0}), 10, np.random.default_rng(0))
    with pytest.raises(MpiLidarError, match="positive amplitudes"):
        posterior_estimates(np.zeros((1, 8)), Config(), np.random.default_rng(0))
