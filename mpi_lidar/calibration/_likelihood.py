"""The Student-t likelihood behind :func:`mpi_lidar.calibration.sensor_scale.estimate_sensor_scale`.

Residuals r_f of F frequencies are fitted as t-distributed with ``STUDENT_DOF`` degrees of freedom, centre the
offset mu_f and scale k eta sqrt(S1), S1 the variance (S1) of :mod:`mpi_lidar.calibration.sensor_scale` built from
the noise model's sd_f at the amplitude A_f / lambda. The parameters are log lambda, log eta (left out where it is
fixed) and the offsets; the noise model is tabulated once on a log grid of amplitudes (:class:`NoiseTable`).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from functools import lru_cache

import numpy as np
from numpy.typing import NDArray

from mpi_lidar.config import SensorConfig
from mpi_lidar.physics.noise import depth_noise_m
from mpi_lidar.physics.robust import robust_sigma

# Where the median amplitude would read as this range of V^2 the unit is looked for (wider than any sensor's).
MEDIAN_AMPLITUDE_RANGE_V2 = (1e-7, 1e2)

# Degrees of freedom of the Student-t the residuals are fitted with: heavy enough tails that a few plane leftovers
# do not inflate the noise, light enough that Gaussian noise loses little (its scale efficiency is about 0.9).
STUDENT_DOF = 6.0
# A pixel with a residual beyond this many standard deviations is an outlier, left out of the next fit (Gaussian
# noise has one such pixel in some 4e5 at four frequencies).
OUTLIER_SIGMAS = 5.0
# Pixels of the coarse profile over the amplitude scale that starts the fit.
START_PIXELS = 2_000
# Step of that profile in log amplitude scale [1]: the optimizer refines it.
START_STEP = 0.25
# The amplitude scale is looked for where the median amplitude reads as MEDIAN_AMPLITUDE_RANGE_V2 (the amplitude
# unit's search range, wider than any sensor's valid amplitudes); the noise scale within this factor of the model
# either way.
NOISE_SCALE_RANGE = 1e3
# Grid of the tabulated noise model: points per decade of amplitude (log-log interpolation errs by ~1e-4).
TABLE_POINTS_PER_DECADE = 40


@lru_cache(maxsize=8)
def gaussian_t_scale(dof: float) -> float:
    """The scale k of the Student-t that maximum likelihood fits to Gaussian noise of unit standard deviation.

    k solves E_z[(nu + 1) z^2 / (nu k^2 + z^2)] = 1 for z ~ N(0, 1), the t's scale score at zero; the expectation
    is a Gauss-Hermite sum. Dividing a fitted t's scale by k gives the Gaussian standard deviation.

    Parameters
    ----------
    dof : float
        The t's degrees of freedom nu (positive; large values approach the Gaussian, k -> 1). [1]

    Returns
    -------
    float
        The scale k. [1]
    """
    from scipy.optimize import brentq

    nodes, weights = np.polynomial.hermite_e.hermegauss(120)
    weights = weights / weights.sum()

    def score(k: float) -> float:
        return float(weights @ ((dof + 1) * nodes**2 / (dof * k**2 + nodes**2))) - 1.0

    return float(brentq(score, 0.1, 10.0, xtol=1e-14))


class NoiseTable:
    """log sd_f of the noise model (:func:`depth_noise_m`) and its slope d log sd / d log A, tabulated on an even
    grid of log amplitudes [log V^2] and interpolated linearly (held at the grid's ends)."""

    def __init__(self, sensor: SensorConfig, frequencies_hz: tuple[float, ...], low: float, high: float):
        self.step = np.log(10.0) / TABLE_POINTS_PER_DECADE
        grid = np.arange(low - self.step, high + 2 * self.step, self.step)
        self.start = float(grid[0])
        amplitude = np.repeat(np.exp(grid)[:, None], len(frequencies_hz), axis=1)
        self.log_sd = np.log(depth_noise_m(sensor, frequencies_hz, amplitude))
        self.slope = np.gradient(self.log_sd, grid, axis=0)
        self.columns = np.arange(len(frequencies_hz))[None, :]

    def __call__(self, log_amplitude_v2: NDArray) -> tuple[NDArray, NDArray]:
        """log sd (n, F) [log m] and its slope (n, F) [1] at log amplitudes (n, F) [log V^2]."""
        position = (log_amplitude_v2 - self.start) / self.step
        below = np.clip(np.floor(position), 0, self.log_sd.shape[0] - 2).astype(np.intp)
        fraction = np.clip(position - below, 0.0, 1.0)
        return (self._at(self.log_sd, below, fraction), self._at(self.slope, below, fraction))

    def _at(self, table: NDArray, below: NDArray, fraction: NDArray) -> NDArray:
        low = table[below, self.columns]
        return low + fraction * (table[below + 1, self.columns] - low)


@dataclass
class Likelihood:
    """The Student-t negative log-likelihood of the residuals and its per-pixel gradients.

    Parameters theta: log lambda, log eta (left out where fixed), then m_f, the offsets mu_f in units of each
    column's robust spread (so that every parameter is of order one for the optimizer).
    """

    log_amplitude: NDArray
    residual: NDArray
    leverage: NDArray
    frequencies_hz: tuple[float, ...]
    sensor: SensorConfig
    fixed_noise_scale: float | None
    dof: float = STUDENT_DOF
    table: NoiseTable = field(init=False)
    bounds: list[tuple[float, float]] = field(init=False)
    unit_m: NDArray = field(init=False)
    k: float = field(init=False)
    own_weight: NDArray = field(init=False)
    shared_weight: NDArray = field(init=False)

    def __post_init__(self) -> None:
        median = float(np.median(self.log_amplitude))
        low, high = (median - np.log(MEDIAN_AMPLITUDE_RANGE_V2[1]), median - np.log(MEDIAN_AMPLITUDE_RANGE_V2[0]))
        self.bounds = [(low, high)]
        if self.fixed_noise_scale is None:
            self.bounds.append((-np.log(NOISE_SCALE_RANGE), np.log(NOISE_SCALE_RANGE)))
        self.bounds += [(-np.inf, np.inf)] * len(self.frequencies_hz)
        # Every amplitude the bounds can make of the pixels' lies on the table.
        self.table = NoiseTable(self.sensor, self.frequencies_hz, float(self.log_amplitude.min()) - high,
                                 float(self.log_amplitude.max()) - low)
        spread = robust_sigma(self.residual - np.median(self.residual, axis=0), axis=0)
        self.unit_m = np.where(spread > 0, spread, 1e-3)
        self.k = gaussian_t_scale(self.dof)
        frequencies = len(self.frequencies_hz)
        # (S1): Var r_f = a s_f^2 + b sum_g s_g^2 per pixel.
        self.own_weight = 1.0 - 2.0 * self.leverage / frequencies
        self.shared_weight = self.leverage / frequencies**2

    @property
    def fits_noise(self) -> bool:
        return self.fixed_noise_scale is None

    def split(self, theta: NDArray) -> tuple[float, float, NDArray]:
        """log lambda, log eta and the offsets mu_f [m] of a parameter vector."""
        if self.fixed_noise_scale is None:
            return float(theta[0]), float(theta[1]), theta[2:] * self.unit_m
        return float(theta[0]), float(np.log(self.fixed_noise_scale)), theta[1:] * self.unit_m

    def terms(self, theta: NDArray, rows: slice | NDArray = slice(None)
              ) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """Negative log-likelihood per pixel (n,) and its gradient per pixel (n, P) (constants left out)."""
        log_scale, log_noise, offsets = self.split(theta)
        log_sd, slope = self.table(self.log_amplitude[rows] - log_scale)
        own = np.exp(2 * log_sd)
        shared = own.sum(1, keepdims=True)
        a, b = self.own_weight[rows, None], self.shared_weight[rows, None]
        variance = a * own + b * shared
        sigma = self.k * np.exp(log_noise) * np.sqrt(variance)
        deviation = self.residual[rows] - offsets
        z2 = (deviation / sigma) ** 2
        nll = np.log(sigma) + 0.5 * (self.dof + 1) * np.log1p(z2 / self.dof)
        d_log_sigma = 1.0 - (self.dof + 1) * z2 / (self.dof + z2)  # d nll / d log sigma
        # d log lambda moves every log amplitude by -1: d log sigma / d log lambda from (S1) and the slopes.
        d_sigma_d_scale = -(a * own * slope + b * (own * slope).sum(1, keepdims=True)) / variance
        d_offset = -(self.dof + 1) * deviation / (self.dof * sigma**2 + deviation**2) * self.unit_m
        columns = [(d_log_sigma * d_sigma_d_scale).sum(1)]
        if self.fits_noise:
            columns.append(d_log_sigma.sum(1))
        gradient = np.column_stack([*columns, d_offset])
        return nll.sum(1), gradient

    def value_and_gradient(self, theta: NDArray) -> tuple[float, NDArray]:
        nll, gradient = self.terms(theta)
        return float(nll.sum()), gradient.sum(0)

    def start(self) -> NDArray[np.float64]:
        """A starting point: the best log lambda of a coarse grid, with eta and the offsets profiled robustly on
        at most ``START_PIXELS`` pixels."""
        n = self.log_amplitude.shape[0]
        rows = np.linspace(0, n - 1, min(n, START_PIXELS)).round().astype(np.intp)
        offsets = np.median(self.residual[rows], axis=0) / self.unit_m
        low, high = self.bounds[0]
        best: tuple[float, NDArray] | None = None
        for log_scale in np.arange(low, high, START_STEP):
            theta = self._profiled(log_scale, offsets, rows)
            value = float(self.terms(theta, rows)[0].sum())
            if best is None or value < best[0]:
                best = (value, theta)
        assert best is not None  # the grid is never empty: the bounds span many decades
        return best[1]

    def _profiled(self, log_scale: float, offsets: NDArray, rows: NDArray) -> NDArray[np.float64]:
        """Parameters at ``log_scale`` with eta from the median of |z| (the Gaussian's is 0.6745)."""
        if not self.fits_noise:
            return np.concatenate([[log_scale], offsets])
        theta = np.concatenate([[log_scale, 0.0], offsets])
        log_sd, _ = self.table(self.log_amplitude[rows] - log_scale)
        deviation = self.residual[rows] - offsets * self.unit_m
        ratio = np.median(np.abs(deviation) / np.exp(log_sd)) / 0.6745
        theta[1] = np.clip(np.log(max(ratio, 1e-300)), *self.bounds[1])
        return theta

    def outlying(self, theta: NDArray) -> NDArray[np.bool_]:
        """Pixels (n,) with a residual beyond ``OUTLIER_SIGMAS`` standard deviations (S1) of its offset."""
        log_scale, log_noise, offsets = self.split(theta)
        log_sd, _ = self.table(self.log_amplitude - log_scale)
        own = np.exp(2 * log_sd)
        variance = self.own_weight[:, None] * own + self.shared_weight[:, None] * own.sum(1, keepdims=True)
        z = np.abs(self.residual - offsets) / (np.exp(log_noise) * np.sqrt(variance))
        return np.asarray((z > OUTLIER_SIGMAS).any(1))

    def fit(self) -> tuple[NDArray[np.float64], bool]:
        """The maximum-likelihood parameters, and whether the optimizer converged."""
        from scipy.optimize import minimize

        found = minimize(self.value_and_gradient, self.start(), jac=True, method="L-BFGS-B", bounds=self.bounds,
                         options={"maxiter": 500, "ftol": 1e-13, "gtol": 1e-8})
        # The line search may give up at the optimum itself, where the gradient is all rounding: a gradient below
        # a hundredth of the score's own spread (about sqrt(n)) leaves the parameters within a hundredth of a sigma.
        settled = np.abs(found.jac).max() <= 0.01 * np.sqrt(self.residual.shape[0])
        return np.asarray(found.x, dtype=np.float64), bool(found.success or settled)

    def covariance(self, theta: NDArray) -> NDArray[np.float64]:
        """Sandwich covariance H^-1 J H^-1 of the parameters: H from central differences of the gradient, J the
        sum of the per-pixel scores' outer products. inf on the diagonal where H is singular."""
        step = 1e-4
        hessian = np.empty((theta.size, theta.size))
        for j in range(theta.size):
            shift = np.zeros(theta.size)
            shift[j] = step
            hessian[:, j] = (self.value_and_gradient(theta + shift)[1]
                             - self.value_and_gradient(theta - shift)[1]) / (2 * step)
        hessian = 0.5 * (hessian + hessian.T)
        scores = self.terms(theta)[1]
        try:
            inverse = np.linalg.inv(hessian)
        except np.linalg.LinAlgError:
            return np.diag(np.full(theta.size, np.inf))
        covariance = inverse @ (scores.T @ scores) @ inverse
        if not np.all(np.isfinite(covariance)) or np.any(np.diag(covariance) < 0):
            return np.diag(np.full(theta.size, np.inf))
        return covariance

