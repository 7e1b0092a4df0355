"""The reciprocal prior as the Bayes limit sees it: its parameterisation, log densities and sampling.

Parameterisation (reciprocal prior): the likelihood depends on theta only through d_AS, d_AB, the albedo
a = rho_SAS = rho_SAB = rho_BAS and q = rho_ABA = kappa * b, whose prior density is that of a product of two
uniforms, p(q) = ln(hi(q) / lo(q)) / ((b1 - b0)(k1 - k0)) with lo = max(b0, q / k1), hi = min(b1, q / k0).
With ``no_multipath_fraction`` = pi0 > 0 the prior also puts mass pi0 on q = 0 (one path); that component
gets its own proposal and the two are mixed with equal probability.

With a log-uniform coupling kappa ~ 1 / (kappa ln(k1 / k0)) (``PriorConfig.coupling_distribution``),
p(q) = (hi(q) - lo(q)) / ((b1 - b0) q ln(k1 / k0)) with the same lo and hi.

d_AS prior: uniform over ``d_as_m``, or log-uniform (density 1 / (d ln(high / low)),
``PriorConfig.d_as_distribution``).
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from mpi_lidar.config import Config, PriorConfig
from mpi_lidar.errors import MpiLidarError


def check_supported(config: Config) -> None:
    """Refuse a configuration whose limit this module cannot compute: a reciprocal prior with noise is needed."""
    if config.prior.scheme != "reciprocal":
        raise MpiLidarError(f"the Bayes limit supports the reciprocal prior only, not {config.prior.scheme!r}")
    if config.simulator.noise_scale <= 0:
        raise MpiLidarError("the Bayes limit needs simulator.noise_scale > 0 (without noise the posterior is a point)")
    if config.prior.d_as_m[1] <= config.prior.d_as_m[0] or config.prior.albedo[1] <= config.prior.albedo[0]:
        raise MpiLidarError("the Bayes limit needs non-degenerate d_as_m and albedo ranges")


def log_coupling_density(q: NDArray[np.float64], prior: PriorConfig) -> NDArray[np.float64]:
    """Log prior density of rho_ABA = kappa * b for b ~ U(albedo) and kappa ~ U(coupling), or log-uniform over it
    (``prior.coupling_distribution``). [log 1/1]"""
    b0, b1 = prior.albedo
    k0, k1 = prior.coupling
    q = np.asarray(q, dtype=np.float64)
    if b1 <= b0 or k1 <= k0:
        raise MpiLidarError("the Bayes limit needs non-degenerate albedo and coupling ranges")
    with np.errstate(divide="ignore", invalid="ignore"):
        lo = np.maximum(b0, q / k1)
        hi = np.minimum(b1, q / k0) if k0 > 0 else np.full_like(q, b1)
        if prior.coupling_distribution == "log_uniform":
            dens = (hi - lo) / ((b1 - b0) * q * np.log(k1 / k0))
        else:
            dens = np.log(hi / lo) / ((b1 - b0) * (k1 - k0))
        out = np.where((q > 0) & (hi > lo), np.log(np.maximum(dens, 1e-300)), -np.inf)
    return out


def sample_coupling(prior: PriorConfig, shape: tuple[int, ...], rng: np.random.Generator) -> NDArray[np.float64]:
    if prior.coupling_distribution == "log_uniform":
        low, high = prior.coupling
        kappa = np.exp(rng.uniform(np.log(low), np.log(high), shape))
    else:
        kappa = rng.uniform(*prior.coupling, shape)
    return kappa * rng.uniform(*prior.albedo, shape)


def log_uniform(x: NDArray[np.float64], interval: tuple[float, float]) -> NDArray[np.float64]:
    lo, hi = interval
    inside = (x >= lo) & (x <= hi)
    return np.where(inside, -np.log(hi - lo) if hi > lo else 0.0, -np.inf)


def log_d_as_density(d_as_m: NDArray[np.float64], prior: PriorConfig) -> NDArray[np.float64]:
    """Log prior density of d_AS: uniform over ``prior.d_as_m``, or log-uniform, 1 / (d ln(high / low)). [log 1/m]"""
    d = np.asarray(d_as_m, dtype=np.float64)
    if prior.d_as_distribution == "uniform":
        return log_uniform(d, prior.d_as_m)
    lo, hi = prior.d_as_m
    inside = (d >= lo) & (d <= hi)
    # ln of the clamped value: proposals land outside the support (even below 0), where the density is 0.
    return np.where(inside, -np.log(np.clip(d, lo, hi)) - np.log(np.log(hi / lo)), -np.inf)


def full_theta(d_as, d_ab, a, q) -> NDArray[np.float64]:
    return np.stack([d_as, d_ab, a, a, q, a], axis=-1)
