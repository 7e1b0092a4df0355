"""The Bayes limit: the best any estimator can do from depth and amplitude at the configured frequencies.

For a measurement y (depth d_k [m] and amplitude A_k [V^2] at each frequency) the posterior over the scene
parameters is p(theta | y) ~ p(theta) L(theta; y). Under the moment-matched sensor
(:mod:`mpi_lidar.physics.moments`) the quadratures (P_k, Q_k) = A_k (cos phi_k, sin phi_k),
phi_k = 4 pi f_k d_k / c (eq 5-7 inverted), are independent across frequencies and Gaussian with the exact
mean and 2x2 covariance of eq 4 and 16-30. The map (P, Q) -> (d, A) has Jacobian A (4 pi f / c), which does
not depend on theta, so L(theta; y) = prod_k N((P_k, Q_k); mu_k(theta), Sigma_k(theta)) up to a constant.
The posterior median of d_AS minimises the expected absolute error (lowest MAE), its mean the expected
squared error (lowest RMSE).

Parameterisation (reciprocal prior): the likelihood depends on theta only through d_AS, d_AB, the albedo
a = rho_SAS = rho_SAB = rho_BAS and q = rho_ABA = kappa * b, whose prior density is that of a product of two
uniforms, p(q) = ln(hi(q) / lo(q)) / ((b1 - b0)(k1 - k0)) with lo = max(b0, q / k1), hi = min(b1, q / k0).
With ``no_multipath_fraction`` = pi0 > 0 the prior also puts mass pi0 on q = 0 (one path); that component
gets its own proposal and the two are mixed with equal probability.

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

d_AS prior: uniform over ``d_as_m``, or log-uniform (density 1 / (d ln(high / low)),
``PriorConfig.d_as_distribution``).

Range and wrapping: a depth is measured as a phase, wrapped to [0, c / 2f) per frequency (4.8 m at 31.25 MHz).
The likelihood sees the depths only through the phasors exp(i 4 pi f d / c), which do not change when a depth
moves by a whole c / 2f: it is right for wrapped and unwrapped depths alike. The proposal is not: its centre
is a single-path range, by default the weighted depth of the row, which is only meaningful once the depths are
unwrapped. Past 4.8 m give :func:`posterior_estimates` unwrapped depths (as
:func:`mpi_lidar.physics.noise.unwrapped_rows` makes them) or the unwrapped range of each row (``range_m``,
e.g. :func:`mpi_lidar.physics.unwrap.unwrap_depths` ``.range_m``). Within 0.5-12 m a wrong wrap count carries
no posterior mass at 12.5-31.25 MHz: the four phases agree again only 24 m further (c / 2 gcd(f)), and every
other shift that locally fits them best within +-12 m leaves them 2.8 rad off or more (root sum of squares,
at +-10.2 m), against a phase noise of at most 0.25 rad per frequency (12 m, albedo 0.14): a likelihood ratio
below e^-60. So :func:`bayes_limit`, which knows the truth, unwraps its rows with the true wrap count.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from mpi_lidar.config import Config, PriorConfig
from mpi_lidar.errors import MpiLidarError
from mpi_lidar.learning.features import weighted_depth
from mpi_lidar.physics.demod import unambiguous_range
from mpi_lidar.physics.moments import MomentSensor
from mpi_lidar.simulation.sampling import sample_theta

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


@dataclass(frozen=True)
class LimitResult:
    """Bayes limit on a test set drawn from the prior.

    mae_m : MAE of the posterior median against the true d_AS. [m]
    rmse_m : RMSE of the posterior mean. [m]
    mae_se_m, rmse_se_m : Monte-Carlo standard errors over the test rows. [m]
    median_ess : median over rows of the effective sample size. [samples]
    raw_mae_m : MAE of the measured depth at the highest frequency, same rows. [m]
    raw : the measured rows (n, 2F), depths unwrapped with the true wrap count (as measured up to 4.8 m). [m, V^2]
    """

    mae_m: float
    rmse_m: float
    mae_se_m: float
    rmse_se_m: float
    median_ess: float
    raw_mae_m: float
    noise_scale: float
    pool: int
    theta: NDArray[np.float64]
    raw: NDArray[np.float64]
    posterior_median_m: NDArray[np.float64]
    posterior_mean_m: NDArray[np.float64]
    ess: NDArray[np.float64]


def _check(config: Config) -> None:
    if config.prior.scheme != "reciprocal":
        raise MpiLidarError(f"the Bayes limit supports the reciprocal prior only, not {config.prior.scheme!r}")
    if config.simulator.noise_scale <= 0:
        raise MpiLidarError("the Bayes limit needs simulator.noise_scale > 0 (without noise the posterior is a point)")
    if config.prior.d_as_m[1] <= config.prior.d_as_m[0] or config.prior.albedo[1] <= config.prior.albedo[0]:
        raise MpiLidarError("the Bayes limit needs non-degenerate d_as_m and albedo ranges")


def log_coupling_density(q: NDArray[np.float64], prior: PriorConfig) -> NDArray[np.float64]:
    """Log prior density of rho_ABA = kappa * b for kappa ~ U(coupling), b ~ U(albedo). [log 1/1]"""
    b0, b1 = prior.albedo
    k0, k1 = prior.coupling
    q = np.asarray(q, dtype=np.float64)
    if b1 <= b0 or k1 <= k0:
        raise MpiLidarError("the Bayes limit needs non-degenerate albedo and coupling ranges")
    with np.errstate(divide="ignore", invalid="ignore"):
        lo = np.maximum(b0, q / k1)
        hi = np.minimum(b1, q / k0) if k0 > 0 else np.full_like(q, b1)
        dens = np.log(hi / lo) / ((b1 - b0) * (k1 - k0))
        out = np.where((q > 0) & (hi > lo), np.log(np.maximum(dens, 1e-300)), -np.inf)
    return out


def _sample_coupling(prior: PriorConfig, shape: tuple[int, ...], rng: np.random.Generator) -> NDArray[np.float64]:
    return rng.uniform(*prior.coupling, shape) * rng.uniform(*prior.albedo, shape)


def _log_uniform(x: NDArray[np.float64], interval: tuple[float, float]) -> NDArray[np.float64]:
    lo, hi = interval
    inside = (x >= lo) & (x <= hi)
    return np.where(inside, -np.log(hi - lo) if hi > lo else 0.0, -np.inf)


def log_d_as_density(d_as_m: NDArray[np.float64], prior: PriorConfig) -> NDArray[np.float64]:
    """Log prior density of d_AS: uniform over ``prior.d_as_m``, or log-uniform, 1 / (d ln(high / low)). [log 1/m]"""
    d = np.asarray(d_as_m, dtype=np.float64)
    if prior.d_as_distribution == "uniform":
        return _log_uniform(d, prior.d_as_m)
    lo, hi = prior.d_as_m
    inside = (d >= lo) & (d <= hi)
    # ln of the clamped value: proposals land outside the support (even below 0), where the density is 0.
    return np.where(inside, -np.log(np.clip(d, lo, hi)) - np.log(np.log(hi / lo)), -np.inf)


def _unwrap_by_truth(depth_m: NDArray[np.float64], true_d_as_m: NDArray[np.float64],
                     frequencies_hz: NDArray[np.float64], c: float) -> NDArray[np.float64]:
    """Measured depths (n, F) moved by whole unambiguous ranges c / 2f to within half of one of the true d_AS. [m]

    The wrap count a simulation knows; rows within half a range of the truth (every row of a prior below
    2.4 m) are returned unchanged, bit for bit.
    """
    ambiguity = unambiguous_range(frequencies_hz, c)[None, :]
    wraps = np.round((true_d_as_m[:, None] - depth_m) / ambiguity)
    return depth_m + wraps * ambiguity


def _full_theta(d_as, d_ab, a, q) -> NDArray[np.float64]:
    return np.stack([d_as, d_ab, a, a, q, a], axis=-1)


def _t_logpdf(x: NDArray[np.float64], nu: float) -> NDArray[np.float64]:
    from scipy.special import gammaln

    return gammaln((nu + 1) / 2) - gammaln(nu / 2) - 0.5 * np.log(nu * np.pi) - (nu + 1) / 2 * np.log1p(x * x / nu)


class _Posterior:
    """Per-row importance sampling of the posterior of d_AS given raw measurements."""

    def __init__(self, config: Config):
        _check(config)
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
        theta = _full_theta(d, np.zeros_like(d), a, np.zeros_like(d))
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
            theta = _full_theta(d, d_ab, a, q)
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
            log_prior = log_d_as_density(d_as, prior) + _log_uniform(a, prior.albedo)
            multi_prior = _log_uniform(d_ab, prior.d_ab_m) + log_coupling_density(q, prior)
            log_prior = log_prior + np.where(multi, multi_prior, 0.0)
            log_w = log_prior - log_prop - np.where(multi, log_pq, 0.0) + log_mix
            ok = np.isfinite(log_w)
            theta = _full_theta(d_as, d_ab, np.where(ok, a, 0.5), q)
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
            q = _sample_coupling(prior, (n, m), rng)
            log_q = _log_uniform(d_ab, prior.d_ab_m) + log_coupling_density(q, prior)
            return d_ab, q, np.where(np.isfinite(log_q), log_q, 0.0)
        centres, cov = gauss
        k = centres.shape[1]
        chol = np.linalg.cholesky(cov)
        pick = rng.integers(0, k, (n, m))
        eps = rng.standard_normal((n, m, 2))
        g = np.take_along_axis(centres, pick[..., None], axis=1) + np.einsum("nij,nmj->nmi", chol, eps)
        from_prior = rng.random((n, m)) < DEFENSIVE
        d_ab = np.where(from_prior, rng.uniform(*prior.d_ab_m, (n, m)), g[..., 0])
        q = np.where(from_prior, _sample_coupling(prior, (n, m), rng), g[..., 1])
        log_prior = _log_uniform(d_ab, prior.d_ab_m) + log_coupling_density(q, prior)
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


def posterior_estimates(raw: NDArray, config: Config, rng: np.random.Generator, pool: int = DEFAULT_POOL,
                        stages: int = DEFAULT_STAGES, range_m: NDArray | None = None) -> PosteriorEstimates:
    """Posterior median, mean, std of d_AS and the effective sample size for each raw row (n, 2F) [m, V^2].

    Uses the exact Gaussian likelihood of the moment-matched sensor of ``config`` (its noise scale included)
    and the configured (reciprocal) prior; ``pool`` particles per row at the last stage. ``range_m`` (n,): the
    unwrapped single-path range of each row, where the proposal is centred [m]; default the weighted depth of
    the rows, whose depths must then be unwrapped. The likelihood takes the depths modulo c / 2f, so wrapped
    depths with their unwrapped ``range_m`` give the same estimates as unwrapped depths.
    """
    return _Posterior(config).estimate(np.asarray(raw, dtype=np.float64), rng, pool, stages, range_m)


def bayes_limit(config: Config, n_test: int, rng: np.random.Generator, pool: int = DEFAULT_POOL,
                stages: int = DEFAULT_STAGES) -> LimitResult:
    """The Bayes limit on ``n_test`` rows drawn from the prior and measured by the moment-matched sensor.

    Returns the MAE of the posterior median and the RMSE of the posterior mean, with their Monte-Carlo
    standard errors over the test rows, the median effective sample size and the raw (highest-frequency)
    MAE of the same rows. Depths past an unambiguous range are unwrapped with the true wrap count first.
    """
    if n_test < 2:
        raise MpiLidarError(f"n_test must be at least 2, got {n_test}")
    _check(config)
    theta = sample_theta(config.prior, n_test, rng)
    depth, amplitude = MomentSensor(config).measure(theta, rng)
    # The wrap count is taken from the truth: at these frequencies no other count carries posterior mass
    # within 24 m (module docstring). A real pipeline unwraps the measured depths itself instead.
    depth = _unwrap_by_truth(depth, theta[:, 0], np.asarray(config.frequencies_hz, dtype=np.float64),
                             config.sensor.speed_of_light_m_per_s)
    raw = np.hstack([depth, amplitude])
    est = posterior_estimates(raw, config, rng, pool=pool, stages=stages)
    truth = theta[:, 0]
    abs_err = np.abs(est.median_m - truth)
    sq_err = (est.mean_m - truth) ** 2
    rmse = float(np.sqrt(sq_err.mean()))
    return LimitResult(
        mae_m=float(abs_err.mean()),
        rmse_m=rmse,
        mae_se_m=float(abs_err.std(ddof=1) / np.sqrt(n_test)),
        rmse_se_m=float(sq_err.std(ddof=1) / np.sqrt(n_test) / (2 * max(rmse, 1e-300))),
        median_ess=float(np.median(est.ess)),
        raw_mae_m=float(np.abs(depth[:, -1] - truth).mean()),
        noise_scale=config.simulator.noise_scale,
        pool=pool,
        theta=theta,
        raw=raw,
        posterior_median_m=est.median_m,
        posterior_mean_m=est.mean_m,
        ess=est.ess,
    )
