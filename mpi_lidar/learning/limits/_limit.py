"""The Bayes limit of a configuration, and the posterior estimates of measured rows.

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

from mpi_lidar.config import Config
from mpi_lidar.errors import MpiLidarError
from mpi_lidar.learning.limits._prior import check_supported
from mpi_lidar.learning.limits._sampler import DEFAULT_POOL, DEFAULT_STAGES, Posterior, PosteriorEstimates
from mpi_lidar.physics.demod import unambiguous_range
from mpi_lidar.physics.moments import MomentSensor
from mpi_lidar.simulation.sampling import sample_theta


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


def unwrap_by_truth(depth_m: NDArray[np.float64], true_d_as_m: NDArray[np.float64],
                     frequencies_hz: NDArray[np.float64], c: float) -> NDArray[np.float64]:
    """Measured depths (n, F) moved by whole unambiguous ranges c / 2f to within half of one of the true d_AS. [m]

    The wrap count a simulation knows; rows within half a range of the truth (every row of a prior below
    2.4 m) are returned unchanged, bit for bit.
    """
    ambiguity = unambiguous_range(frequencies_hz, c)[None, :]
    wraps = np.round((true_d_as_m[:, None] - depth_m) / ambiguity)
    return depth_m + wraps * ambiguity


def posterior_estimates(raw: NDArray, config: Config, rng: np.random.Generator, pool: int = DEFAULT_POOL,
                        stages: int = DEFAULT_STAGES, range_m: NDArray | None = None) -> PosteriorEstimates:
    """Posterior median, mean, std of d_AS and the effective sample size for each raw row (n, 2F) [m, V^2].

    Uses the exact Gaussian likelihood of the moment-matched sensor of ``config`` (its noise scale included)
    and the configured (reciprocal) prior; ``pool`` particles per row at the last stage. ``range_m`` (n,): the
    unwrapped single-path range of each row, where the proposal is centred [m]; default the weighted depth of
    the rows, whose depths must then be unwrapped. The likelihood takes the depths modulo c / 2f, so wrapped
    depths with their unwrapped ``range_m`` give the same estimates as unwrapped depths.
    """
    return Posterior(config).estimate(np.asarray(raw, dtype=np.float64), rng, pool, stages, range_m)


def bayes_limit(config: Config, n_test: int, rng: np.random.Generator, pool: int = DEFAULT_POOL,
                stages: int = DEFAULT_STAGES) -> LimitResult:
    """The Bayes limit on ``n_test`` rows drawn from the prior and measured by the moment-matched sensor.

    Returns the MAE of the posterior median and the RMSE of the posterior mean, with their Monte-Carlo
    standard errors over the test rows, the median effective sample size and the raw (highest-frequency)
    MAE of the same rows. Depths past an unambiguous range are unwrapped with the true wrap count first.
    """
    if n_test < 2:
        raise MpiLidarError(f"n_test must be at least 2, got {n_test}")
    check_supported(config)
    theta = sample_theta(config.prior, n_test, rng)
    depth, amplitude = MomentSensor(config).measure(theta, rng)
    # The wrap count is taken from the truth: at these frequencies no other count carries posterior mass
    # within 24 m (module docstring). A real pipeline unwraps the measured depths itself instead.
    depth = unwrap_by_truth(depth, theta[:, 0], np.asarray(config.frequencies_hz, dtype=np.float64),
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
