"""The Bayes limit: the best any estimator can do from depth and amplitude at the configured frequencies.

For a measurement y (depth d_k [m] and amplitude A_k [V^2] at each frequency) the posterior over the scene
parameters is p(theta | y) ~ p(theta) L(theta; y). Under the moment-matched sensor
(:mod:`mpi_lidar.physics.moments`) the quadratures (P_k, Q_k) = A_k (cos phi_k, sin phi_k),
phi_k = 4 pi f_k d_k / c (eq 5-7 inverted), are independent across frequencies and Gaussian with the exact
mean and 2x2 covariance of eq 4 and 16-30. The map (P, Q) -> (d, A) has Jacobian A (4 pi f / c), which does
not depend on theta, so L(theta; y) = prod_k N((P_k, Q_k); mu_k(theta), Sigma_k(theta)) up to a constant.
The posterior median of d_AS minimises the expected absolute error (lowest MAE), its mean the expected
squared error (lowest RMSE).

The parts, each private: ``_prior`` (the reciprocal prior: parameterisation, densities, sampling),
``_sampler`` (the per-row importance sampler and its proposal) and ``_limit`` (the limit on rows drawn from the
prior, and the wrapping of depths).
"""

from __future__ import annotations

from mpi_lidar.learning.limits._limit import LimitResult, bayes_limit, posterior_estimates
from mpi_lidar.learning.limits._prior import log_coupling_density, log_d_as_density
from mpi_lidar.learning.limits._sampler import DEFAULT_POOL, DEFAULT_STAGES, PosteriorEstimates, weighted_median

__all__ = [
    "DEFAULT_POOL", "DEFAULT_STAGES", "LimitResult", "PosteriorEstimates", "bayes_limit", "log_coupling_density",
    "log_d_as_density", "posterior_estimates", "weighted_median",
]
