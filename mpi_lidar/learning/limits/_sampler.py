"""The per-row importance sampler of the posterior of d_AS given raw measurements.

Importance sampling with the prior as proposal collapses at low noise (the likelihood pins d_AS and a to
~1e-5 of their prior range). The proposal here is built per row:

1. (d_AB, q) from a proposal over the weakly identified pair: the prior at the first stage, then a mixture
   of the prior (defensive share ``DEFENSIVE``) and a kernel mixture: ``KERNELS`` Gaussians centred on
   particles of the previous stage resampled by weight, with ``BANDWIDTH``^2 times their weighted covariance
   (population Monte Carlo), for ``stages`` stages in all.
2. Given (d_AB, q), d_AS and ln a are nearly pinned by the data: their centre is found by Newton steps on the
   measured phasors with the noiseless (unrounded) moment model, and they are drawn from Student-t
   distributions (``NU`` degrees of freedom) around it whose scales are ``WIDEN`` times the predicted
   standard deviations (from the moment covariance at the measurement).

The weights p(theta) L(theta) / q(theta) are exact, so the estimates are consistent whatever the proposal;
the proposal only sets their variance. Each row reports its Kish effective sample size
(sum w)^2 / sum w^2 over the particles of all stages, which together give the estimates (each stage's
weights are exact, so they can be pooled).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from mpi_lidar.config import Config, PriorConfig
from mpi_lidar.errors import MpiLidarError
from mpi_lidar.learning.features import weighted_depth
from mpi_lidar.learning.limits._prior import (
    check_supported,
    full_theta,
    log_coupling_density,
    log_d_as_density,
    log_uniform,
    sample_coupling,
)
from mpi_lidar.physics.moments import MomentSensor

DEFAULT_POOL = 2000
DEFAULT_STAGES = 4
DEFENSIVE = 0.2
KERNELS = 64
BANDWIDTH = 0.5
NU = 5.0
WIDEN = 1.5
# Floor of the proposal scale of d_AS [m] and of ln a [1], against a predicted standard deviation of zero.
DEPTH_FLOOR_M = 1e-6
LOG_ALBEDO_FLOOR = 1e-6
# Thetas per block of likelihood evaluations (memory: ~1 kB per theta).
BLOCK_THETAS = 100_000


@dataclass(frozen=True)
class PosteriorEstimates:
    """Per-row posterior summaries of d_AS, shape (n,) each.

    median_m : posterior median (the MAE-optimal estimate). [m]
    mean_m : posterior mean (the RMSE-optimal estimate). [m]
    std_m : posterior standard deviation. [m]
    ess : Kish effective sample size of all stages' particles. [samples] 0 marks a row where no particle
        had positive weight (a measurement the prior can hardly produce, e.g. rho_ABA = 1 exactly); its
        estimates are then the single-path weighted depth and its std 0.
    """

    median_m: NDArray[np.float64]
    mean_m: NDArray[np.float64]
    std_m: NDArray[np.float64]
    ess: NDArray[np.float64]


def _t_logpdf(x: NDArray[np.float64], nu: float) -> NDArray[np.float64]:
    from scipy.special import gammaln

    return gammaln((nu + 1) / 2) - gammaln(nu / 2) - 0.5 * np.log(nu * np.pi) - (nu + 1) / 2 * np.log1p(x * x / nu)


class Posterior:
    """Per-row importance sampling of the posterior of d_AS given raw measurements."""

    def __init__(self, config: Config):
        check_supported(config)
        self.config = config
        self.prior = config.prior
        self.exact = MomentSensor(config)
        self.smooth = MomentSensor(config.replace(simulator={"round_photons": False}))
        self.freqs = np.asarray(config.frequencies_hz, dtype=np.float64)
        self.c = config.sensor.speed_of_light_m_per_s
        self.omega = 4 * np.pi * self.freqs / self.c

    # Measurement side ---------------------------------------------------------------------------------
    def measured(self, raw: NDArray[np.float64]):
        f = self.freqs.size
        depth, amplitude = raw[:, :f], raw[:, f:]
        return amplitude * np.exp(1j * self.omega * depth), depth, amplitude

    def noise_std(self, raw: NDArray[np.float64], range_m: NDArray[np.float64] | None = None) -> NDArray[np.float64]:
        """Std of one quadrature (n, F) for single-path light of the measured amplitude at ``range_m``. [V^2]

        ``range_m`` (n,): the single-path range of each row [m]; default the weighted depth of unwrapped rows.
        """
        f = self.freqs.size
        s = self.config.sensor
        d = weighted_depth(raw, tuple(self.freqs)) if range_m is None else range_m
        a = np.clip(raw[:, 2 * f - 1] * d**2 / s.gamma_r_v2, 1e-6, 1.0)
        theta = full_theta(d, np.zeros_like(d), a, np.zeros_like(d))
        _, cov = self.smooth.quadrature_moments(theta)
        return np.sqrt(0.5 * (cov[..., 0, 0] + cov[..., 1, 1]))

    # Model side -------------------------------------------------------------------------------------
    def _mean_phasor(self, sensor: MomentSensor, theta: NDArray[np.float64]) -> NDArray[np.complex128]:
        mean, _ = sensor.quadrature_moments(theta.reshape(-1, 6))
        return (mean[..., 0] + 1j * mean[..., 1]).reshape(*theta.shape[:-1], self.freqs.size)

    def log_likelihood(self, theta: NDArray[np.float64], p: NDArray, q: NDArray) -> NDArray[np.float64]:
        """Sum over frequencies of the bivariate Gaussian log density of the measured (P, Q); theta (..., 6)."""
        mean, cov = self.exact.quadrature_moments(theta.reshape(-1, 6))
        shape = theta.shape[:-1]
        mean = mean.reshape(*shape, self.freqs.size, 2)
        cov = cov.reshape(*shape, self.freqs.size, 2, 2)
        dp, dq = p - mean[..., 0], q - mean[..., 1]
        sxx, sxy, syy = cov[..., 0, 0], cov[..., 0, 1], cov[..., 1, 1]
        det = np.maximum(sxx * syy - sxy * sxy, 1e-300)
        maha = (syy * dp * dp - 2 * sxy * dp * dq + sxx * dq * dq) / det
        return (-0.5 * maha - 0.5 * np.log(det) - np.log(2 * np.pi)).sum(-1)

    def centre(self, z: NDArray, sigma: NDArray, d_ab: NDArray, q: NDArray, d0: NDArray, a0: NDArray,
               steps: int = 3):
        """Newton steps for (d_AS, ln a) given (d_AB, q) on the noiseless moment model; arrays (n, m)."""
        d, log_a = d0.copy(), np.log(a0)
        amp2 = (np.abs(z) / sigma) ** 2  # (n, F): inverse relative variance of each phasor
        w_d = amp2 * self.omega**2
        for _ in range(steps):
            a = np.exp(log_a)
            theta = full_theta(d, d_ab, a, q)
            model = self._mean_phasor(self.smooth, theta)  # (n, m, F)
            ratio = z[:, None, :] / model
            x = a[..., None] * q[..., None] * np.exp(1j * self.omega * d_ab[..., None])
            slope = 1 + (x / (1 + x)).real  # d ln|m| / d ln a
            dd = (w_d[:, None, :] * np.angle(ratio) / self.omega).sum(-1) / w_d.sum(-1)[:, None]
            lr = np.log(np.abs(ratio)) + 2 * dd[..., None] / d[..., None]
            w_a = amp2[:, None, :] * slope**2
            dla = (w_a * lr / slope).sum(-1) / w_a.sum(-1)
            d = d + dd
            log_a = np.clip(log_a + dla, np.log(1e-4), np.log(2.0))
        a = np.exp(log_a)
        x = a[..., None] * q[..., None] * np.exp(1j * self.omega * d_ab[..., None])
        slope = 1 + (x / (1 + x)).real
        sd_d = 1 / np.sqrt(w_d.sum(-1))[:, None] * np.ones_like(d)
        sd_la = 1 / np.sqrt((amp2[:, None, :] * slope**2).sum(-1))
        return d, log_a, sd_d, sd_la

    # Sampling -------------------------------------------------------------------------------------
    def estimate(self, raw: NDArray[np.float64], rng: np.random.Generator, pool: int, stages: int,
                 range_m: NDArray[np.float64] | None = None):
        raw = np.asarray(raw, dtype=np.float64)
        f = self.freqs.size
        if raw.ndim != 2 or raw.shape[1] != 2 * f:
            raise MpiLidarError(f"expected raw measurements of shape (n, {2 * f}), got {raw.shape}")
        if not (np.isfinite(raw).all() and (raw[:, f:] > 0).all()):
            raise MpiLidarError("posterior estimates need finite measurements with positive amplitudes")
        n = raw.shape[0]
        centre = weighted_depth(raw, tuple(self.freqs)) if range_m is None else np.asarray(range_m, np.float64)
        if centre.shape != (n,) or not (np.isfinite(centre).all() and (centre > 0).all()):
            raise MpiLidarError(f"range_m must hold one finite positive range per row ({n}), got shape {centre.shape}")
        out = [np.empty(n) for _ in range(4)]
        rows_per_block = max(1, BLOCK_THETAS // (pool * 3))
        for start in range(0, n, rows_per_block):
            rows = slice(start, min(n, start + rows_per_block))
            for dst, src in zip(out, self._estimate_block(raw[rows], centre[rows], rng, pool, stages), strict=True):
                dst[rows] = src
        return PosteriorEstimates(*out)

    def _estimate_block(self, raw: NDArray, d0: NDArray, rng: np.random.Generator, pool: int, stages: int):
        """Estimates for the rows ``raw`` whose single-path (unwrapped) range is ``d0`` (n,) [m]."""
        prior = self.prior
        z, _, amplitude = self.measured(raw)
        p_meas, q_meas = z.real, z.imag
        sigma = self.noise_std(raw, d0)
        n = raw.shape[0]
        a0 = np.clip(amplitude[:, -1] * d0**2 / self.config.sensor.gamma_r_v2, 1e-4, 1.0)
        pi0 = prior.no_multipath_fraction
        sizes = [max(64, pool // 4)] * (stages - 1) + [pool]
        gauss = None  # kernel centres (n, K, 2) and covariance (n, 2, 2) of (d_AB, q)
        samples, log_weights = [], []
        for m in sizes:
            d_ab, q, log_pq = self._propose_pair(n, m, gauss, rng)
            multi = np.ones((n, m), dtype=bool)
            log_mix = np.zeros((n, m))
            if pi0 > 0:
                multi = rng.random((n, m)) < (0.5 if pi0 < 1 else 0.0)
                q = np.where(multi, q, 0.0)
                d_ab = np.where(multi, d_ab, 0.0)
                log_pq = np.where(multi, log_pq, 0.0)
                log_mix = np.where(multi, np.log1p(-pi0) - np.log(0.5), np.log(pi0) - np.log(0.5))
            dc, lac, sd_d, sd_la = self.centre(z, sigma, d_ab, q, d0[:, None] * np.ones((n, m)),
                                               a0[:, None] * np.ones((n, m)))
            scale_d = WIDEN * sd_d + DEPTH_FLOOR_M
            scale_la = WIDEN * sd_la + LOG_ALBEDO_FLOOR
            t_d = rng.standard_t(NU, (n, m))
            t_a = rng.standard_t(NU, (n, m))
            d_as = dc + scale_d * t_d
            log_a = lac + scale_la * t_a
            a = np.exp(log_a)
            log_prop = (_t_logpdf(t_d, NU) - np.log(scale_d) + _t_logpdf(t_a, NU) - np.log(scale_la) - log_a)
            log_prior = log_d_as_density(d_as, prior) + log_uniform(a, prior.albedo)
            multi_prior = log_uniform(d_ab, prior.d_ab_m) + log_coupling_density(q, prior)
            log_prior = log_prior + np.where(multi, multi_prior, 0.0)
            log_w = log_prior - log_prop - np.where(multi, log_pq, 0.0) + log_mix
            ok = np.isfinite(log_w)
            theta = full_theta(d_as, d_ab, np.where(ok, a, 0.5), q)
            theta[..., 0] = np.where(ok, d_as, d0[:, None])
            log_l = self.log_likelihood(theta, p_meas[:, None, :], q_meas[:, None, :])
            log_w = np.where(ok, log_w + log_l, -np.inf)
            samples.append(d_as)
            log_weights.append(log_w)
            w = _normalised(log_w)
            gauss = _fit_pair(d_ab, q, np.where(multi, w, 0.0), rng, prior)
        # Every stage's weights p L / q are exact (q is normalised), so all particles count.
        d_as, log_w = np.concatenate(samples, axis=1), np.concatenate(log_weights, axis=1)
        w = _normalised(log_w)
        ess = 1.0 / (w**2).sum(axis=1)
        mean = (w * d_as).sum(axis=1)
        std = np.sqrt(np.maximum((w * (d_as - mean[:, None]) ** 2).sum(axis=1), 0.0))
        median = weighted_median(d_as, w)
        # No particle with positive weight: the measurement lies where the prior puts (almost) no mass.
        lost = ~np.isfinite(log_w).any(axis=1)
        return (np.where(lost, d0, median), np.where(lost, d0, mean), np.where(lost, 0.0, std),
                np.where(lost, 0.0, ess))

    def _propose_pair(self, n: int, m: int, gauss, rng: np.random.Generator):
        """(d_AB, q) of shape (n, m) and the log proposal density at them."""
        prior = self.prior
        if gauss is None:
            d_ab = rng.uniform(*prior.d_ab_m, (n, m))
            q = sample_coupling(prior, (n, m), rng)
            log_q = log_uniform(d_ab, prior.d_ab_m) + log_coupling_density(q, prior)
            return d_ab, q, np.where(np.isfinite(log_q), log_q, 0.0)
        centres, cov = gauss
        k = centres.shape[1]
        chol = np.linalg.cholesky(cov)
        pick = rng.integers(0, k, (n, m))
        eps = rng.standard_normal((n, m, 2))
        g = np.take_along_axis(centres, pick[..., None], axis=1) + np.einsum("nij,nmj->nmi", chol, eps)
        from_prior = rng.random((n, m)) < DEFENSIVE
        d_ab = np.where(from_prior, rng.uniform(*prior.d_ab_m, (n, m)), g[..., 0])
        q = np.where(from_prior, sample_coupling(prior, (n, m), rng), g[..., 1])
        log_prior = log_uniform(d_ab, prior.d_ab_m) + log_coupling_density(q, prior)
        x = np.stack([d_ab, q], -1)[:, :, None, :] - centres[:, None, :, :]  # (n, m, K, 2)
        inv = np.linalg.inv(cov)[:, None, None]
        maha = np.einsum("nmki,nmkij,nmkj->nmk", x, np.broadcast_to(inv, (n, 1, 1, 2, 2)), x)
        log_norm = -np.log(2 * np.pi) - 0.5 * np.log(np.linalg.det(cov))[:, None]
        log_g = np.logaddexp.reduce(-0.5 * maha, axis=-1) - np.log(k) + log_norm
        log_q = np.logaddexp(np.log(DEFENSIVE) + log_prior, np.log1p(-DEFENSIVE) + log_g)
        return d_ab, q, log_q


def _fit_pair(d_ab: NDArray, q: NDArray, w: NDArray, rng: np.random.Generator, prior: PriorConfig):
    """Kernel mixture for the next stage: KERNELS centres resampled by weight, a shared kernel covariance.

    The kernel covariance is BANDWIDTH^2 times the weighted covariance of (d_AB, q) per row, so the mixture
    follows curved posteriors that one Gaussian would cover badly. Where the weights sit on few particles
    that covariance collapses; its floor is the squared spacing of m particles over the prior's range, the
    resolution at which the stage looked.
    """
    n, m = w.shape
    total = w.sum(axis=1, keepdims=True)
    w = np.where(total > 0, w / np.where(total > 0, total, 1.0), 1.0 / m)
    x = np.stack([d_ab, q], -1)
    mean = (w[..., None] * x).sum(1)
    dx = x - mean[:, None, :]
    cov = np.einsum("nm,nmi,nmj->nij", w, dx, dx)
    u = (rng.random((n, 1)) + np.arange(KERNELS)[None, :]) / KERNELS
    cdf = np.cumsum(w, axis=1)
    idx = np.minimum((cdf[:, None, :] < u[:, :, None]).sum(-1), m - 1)
    centres = np.take_along_axis(x, idx[..., None], axis=1)
    spacing = np.array([prior.d_ab_m[1] - prior.d_ab_m[0], prior.coupling[1] * prior.albedo[1]]) / np.sqrt(m)
    floor = np.diag(np.maximum(spacing, 1e-6) ** 2)
    return centres, BANDWIDTH**2 * cov + floor


def _normalised(log_w: NDArray[np.float64]) -> NDArray[np.float64]:
    """Weights exp(log_w) normalised per row; uniform on rows where every log weight is -inf."""
    top = log_w.max(axis=1, keepdims=True)
    finite = np.isfinite(top)
    w = np.exp(log_w - np.where(finite, top, 0.0))
    w = np.where(finite, w, 1.0)
    return w / w.sum(axis=1, keepdims=True)


def weighted_median(x: NDArray[np.float64], w: NDArray[np.float64]) -> NDArray[np.float64]:
    """Per-row median of samples x (n, m) with non-negative weights w (n, m) summing to 1, interpolated."""
    order = np.argsort(x, axis=1)
    xs = np.take_along_axis(x, order, axis=1)
    ws = np.take_along_axis(w, order, axis=1)
    cdf = np.cumsum(ws, axis=1) - 0.5 * ws
    cdf /= np.maximum(cdf[:, -1:] + 0.5 * ws[:, -1:], 1e-300)
    idx = np.clip((cdf < 0.5).sum(axis=1), 1, x.shape[1] - 1)
    rows = np.arange(x.shape[0])
    lo_c, hi_c = cdf[rows, idx - 1], cdf[rows, idx]
    t = np.clip((0.5 - lo_c) / np.maximum(hi_c - lo_c, 1e-300), 0.0, 1.0)
    return xs[rows, idx - 1] + t * (xs[rows, idx] - xs[rows, idx - 1])
