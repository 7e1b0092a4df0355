"""A scan's amplitude units, noise scale and per-frequency depth offsets, measured on its own flat surfaces.

A scanner reports amplitude in its own units, ``amplitude_units = amplitude_scale x amplitude_V2``; its depth
noise may differ from the noise model (:func:`mpi_lidar.correction.validity.depth_noise_m`) by a factor, the noise
scale eta; and each frequency may read every depth a fixed offset o_f too far. On a flat surface without
multipath, a frequency's depth minus the surface's plane is that frequency's noise plus its offset, so

    r_f ~ mu_f + eta sd_f(A_f / lambda),

with lambda the amplitude scale [units / V^2] and A_f the amplitude the scanner reports. The noise model's shape
tells lambda from eta: the thermal and TIA noise are constant, so at low amplitude sd ~ 1 / A (only the product
lambda eta is seen there), while shot noise grows with the signal, so at high amplitude sd ~ 1 / sqrt(A) (only
lambda eta^2). A scan whose amplitudes span both regimes measures both; where they span one, only a product is
determined, and :class:`SensorScale` says so.

Planes. :func:`flat_surface_residuals` fits each block's plane to the depth averaged over the F frequencies,
d_mean, so that no frequency is fitted more closely than another. With the plane's hat matrix H (leverage h_i of
pixel i, h = 3 / m on average for m pixels), r_f = e_f - (H e_mean)_i, and

    Var r_f = s_f^2 (1 - 2 h_i / F) + h_i / F^2 sum_g s_g^2,                                  (S1)

the degrees of freedom the fit takes: :func:`estimate_sensor_scale` uses (S1), not s_f^2. A plane fitted to the
highest frequency alone would shrink that frequency's variance by (1 - h_i) and inflate the others' by
h_i s_F^2, and its outlier trimming would truncate the highest frequency's residuals only.

Offsets. The plane takes up the offsets' mean, so the residuals show mu_f = o_f - mean_g o_g: only differences
between frequencies are measured, and :attr:`SensorScale.offsets_m` gives them relative to the highest frequency.

Fit. Maximum likelihood of the residuals under a Student-t of ``STUDENT_DOF`` degrees of freedom and scale
k eta sqrt(S1): plane leftovers, flying pixels at edges and wrapped frequencies weigh less than under a Gaussian.
k (:func:`gaussian_t_scale`) makes eta the standard deviation's factor where the noise is Gaussian. The parameters
are log lambda, log eta and mu_f; the model's sd_f is tabulated once on a log grid of amplitudes. The covariance
is the sandwich H^-1 J H^-1 of the per-pixel scores (the t is a working model, the noise Gaussian).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from functools import lru_cache

import numpy as np
from numpy.typing import NDArray

from mpi_lidar.config import SensorConfig
from mpi_lidar.correction.footprint import surface_labels
from mpi_lidar.correction.options import AUTO, CorrectionOptions
from mpi_lidar.correction.scene import SceneGeometry, scene_blocks
from mpi_lidar.correction.validity import depth_noise_m
from mpi_lidar.physics.coupling import DEFAULT_FOOTPRINT_AREA_M2
from mpi_lidar.physics.window import window_corrections_m
from mpi_lidar.scans import geometry
from mpi_lidar.scans.scan import Scan

# Degrees of freedom of the Student-t the residuals are fitted with: heavy enough tails that a few plane leftovers
# do not inflate the noise, light enough that Gaussian noise loses little (its scale efficiency is about 0.9).
STUDENT_DOF = 6.0
# A measurement is significant with at least this many pixels ...
MIN_PIXELS = 200
# ... and the amplitude scale (and a fitted noise scale) known to this relative standard deviation.
MAX_RELATIVE_SIGMA = 0.1
# A pixel with a residual beyond this many standard deviations is an outlier, left out of the next fit (Gaussian
# noise has one such pixel in some 4e5 at four frequencies); at most this many rounds of fits leave outliers out.
OUTLIER_SIGMAS = 5.0
OUTLIER_ROUNDS = 3
# Pixels the likelihood is evaluated on at most (evenly spaced among those given): beyond some 10^5 the sigmas are
# far below the model's own systematic errors.
MAX_PIXELS = 100_000
# Pixels of the coarse profile over the amplitude scale that starts the fit.
START_PIXELS = 2_000
# Step of that profile in log amplitude scale [1]: the optimizer refines it.
START_STEP = 0.25
# The amplitude scale is looked for where the median amplitude reads as this range of V^2 (wider than any sensor's
# valid amplitudes); the noise scale within this factor of the model either way.
MEDIAN_AMPLITUDE_RANGE_V2 = (1e-7, 1e2)
NOISE_SCALE_RANGE = 1e3
# Grid of the tabulated noise model: points per decade of amplitude (log-log interpolation errs by ~1e-4).
TABLE_POINTS_PER_DECADE = 40
# Flat pixels are taken only where the expected multipath bias stays below this [m] at a generous footprint:
# a few times the default effective footprint, or the given one if larger.
MAX_FLAT_BIAS_M = 2e-5
GENEROUS_FOOTPRINT_FACTOR = 4.0
# A block is taken only when its plane (fitted to the highest frequency) kept this share of its pixels: a block
# that straddles a depth edge keeps one side only, and its label speaks for that side alone.
MIN_KEPT_SHARE = 0.9
# A pixel's residuals count when its mean depth lies within this many robust sigmas of its block's plane: wide
# enough that no residual is truncated (a Gaussian passes 6 sigmas once in 5e8), narrow enough to leave out a
# pixel of another surface.
PLANE_WINDOW_SIGMAS = 6.0


@dataclass(frozen=True)
class SensorScale:
    """What a scan's flat surfaces say of its amplitude units, noise and depth offsets (:func:`estimate_sensor_scale`).

    Attributes
    ----------
    amplitude_scale : float
        lambda: the scanner's amplitude unit per V^2 of the noise model, NaN where nothing was measured. [units/V^2]
    amplitude_scale_sigma : float
        Its standard deviation, inf where it is not determined. [units/V^2]
    noise_scale : float
        eta: the depth noise over the noise model's (the fixed value where it was fixed). [1]
    noise_scale_sigma : float
        Its standard deviation (0 where fixed, inf where not determined). [1]
    offsets_m : NDArray[np.float64]
        Depth offset of each frequency (F,) relative to the highest frequency (whose entry is 0): a common offset
        of all frequencies is taken up by the planes and cannot be measured. [m]
    offsets_sigma_m : NDArray[np.float64]
        Their standard deviations (F,). [m]
    pixels : int
        Pixels the fit used.
    significant : bool
        Whether the amplitude scale (and a fitted noise scale) is known to ``MAX_RELATIVE_SIGMA`` on at least
        ``MIN_PIXELS`` pixels.
    reason : str
        Why it is not significant; empty where it is.
    scale_noise_correlation : float
        Correlation of log amplitude_scale and log noise_scale: near 1 in magnitude where only a product of them
        is determined. [1]
    amplitude_decades : float
        log10 of the 95th over the 5th percentile of the pixels' amplitudes: the span that tells the two scales
        apart. [1]
    outliers : int
        Pixels left out for a residual beyond ``OUTLIER_SIGMAS`` standard deviations.
    """

    amplitude_scale: float
    amplitude_scale_sigma: float
    noise_scale: float
    noise_scale_sigma: float
    offsets_m: NDArray[np.float64]
    offsets_sigma_m: NDArray[np.float64]
    pixels: int
    significant: bool
    reason: str
    scale_noise_correlation: float = float("nan")
    amplitude_decades: float = float("nan")
    outliers: int = 0


@dataclass(frozen=True)
class FlatSurfaceResiduals:
    """Each frequency's depth minus its block's plane on a scan's flat surfaces, away from multipath and edges
    (:func:`flat_surface_residuals`).

    Attributes
    ----------
    amplitude : NDArray[np.float64]
        Amplitude (n, F) as the scan reports it. [scanner units]
    residual_m : NDArray[np.float64]
        Depth minus the plane's depth along the pixel's ray (n, F), the plane fitted to the mean depth over the
        frequencies. [m]
    leverage : NDArray[np.float64]
        The plane fit's leverage h of each pixel (n,): its block's hat-matrix diagonal, 3 / m on average. [1]
    pixels : NDArray[np.intp]
        Flat indices (n,) of the pixels in the scan's (H, W) grid.
    blocks : int
        The blocks the pixels lie in.
    """

    amplitude: NDArray[np.float64]
    residual_m: NDArray[np.float64]
    leverage: NDArray[np.float64]
    pixels: NDArray[np.intp]
    blocks: int = 0


def measure_sensor_scale(scan: Scan, usable_depth: NDArray, options: CorrectionOptions, sensor: SensorConfig, *,
                         scene: SceneGeometry | None = None, fix_noise_scale: float | None = None,
                         window: bool = False) -> SensorScale:
    """The amplitude scale, noise scale and depth offsets of a scan, from its flat surfaces; with ``window``, of
    its depths with the integration window's leakage removed (:func:`window_corrections_m`, which reads the
    amplitudes in V^2).

    :func:`flat_surface_residuals` then :func:`estimate_sensor_scale`; the parameters are theirs.
    """
    flat = flat_surface_residuals(scan, usable_depth, options, scene=scene, window_sensor=sensor if window else None)
    return estimate_sensor_scale(flat.amplitude, flat.residual_m, scan.frequencies_hz, sensor,
                                 fix_noise_scale=fix_noise_scale, leverage=flat.leverage)


# --- the estimator -------------------------------------------------------------------------------------------


def estimate_sensor_scale(amplitude: NDArray, residual_m: NDArray, frequencies_hz: tuple[float, ...],
                          sensor: SensorConfig, *, fix_noise_scale: float | None = None,
                          leverage: NDArray | None = None) -> SensorScale:
    """Maximum-likelihood amplitude scale, noise scale and depth offsets of flat-surface residuals.

    Parameters
    ----------
    amplitude : NDArray
        Amplitude (n, F) as the scanner reports it. [scanner units]
    residual_m : NDArray
        Depth minus the surface's plane (n, F) of pixels without multipath. [m]
    frequencies_hz : tuple[float, ...]
        The F modulation frequencies, in the columns' order. [Hz]
    sensor : SensorConfig
        The sensor whose noise model (:func:`~mpi_lidar.correction.validity.depth_noise_m`) the noise is scaled
        from.
    fix_noise_scale : float | None
        Hold the noise scale at this value and fit only the amplitude scale and offsets: where the amplitudes span
        one noise regime only, this gives the amplitude scale the product determines. [1]
    leverage : NDArray | None
        The leverage (n,) of each pixel in the plane fit over the mean depth of the frequencies
        (:attr:`FlatSurfaceResiduals.leverage`), for (S1); None: residuals from the true plane. [1]

    Returns
    -------
    SensorScale
        The estimates, their standard deviations, and whether they are significant.
    """
    if fix_noise_scale is not None and not (np.isfinite(fix_noise_scale) and fix_noise_scale > 0):
        raise ValueError(f"fix_noise_scale must be a positive number, got {fix_noise_scale}")
    freqs = tuple(float(f) for f in frequencies_hz)
    amplitude, residual, lever = _usable_rows(amplitude, residual_m, leverage, len(freqs))
    order = np.argsort(freqs)
    if amplitude.shape[0] < MIN_PIXELS:
        return _nothing_measured(len(freqs), amplitude.shape[0], fix_noise_scale,
                                 f"only {amplitude.shape[0]} flat pixels, at least {MIN_PIXELS} needed")
    outliers = 0
    for _ in range(OUTLIER_ROUNDS + 1):
        model = _Likelihood(np.log(amplitude), residual, lever, freqs, sensor, fix_noise_scale)
        theta, converged = model.fit()
        outlying = model.outlying(theta)
        if not outlying.any():
            break
        # Gross outliers still pull the bounded-influence fit, and all the more the split of lambda from eta where
        # they gather at one end of the amplitudes: they are dropped and the fit repeated.
        outliers += int(outlying.sum())
        amplitude, residual, lever = amplitude[~outlying], residual[~outlying], lever[~outlying]
        if amplitude.shape[0] < MIN_PIXELS:
            return _nothing_measured(len(freqs), amplitude.shape[0], fix_noise_scale,
                                     f"only {amplitude.shape[0]} flat pixels once {outliers} outliers were left out, "
                                     f"at least {MIN_PIXELS} needed")
    covariance = model.covariance(theta)
    return _result(model, theta, covariance, converged, order[-1], _decades(amplitude), amplitude.shape[0], outliers)


def _usable_rows(amplitude: NDArray, residual_m: NDArray, leverage: NDArray | None, frequencies: int
                 ) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
    """The rows with finite residuals and finite positive amplitudes, at most ``MAX_PIXELS`` evenly spaced."""
    amplitude = np.asarray(amplitude, dtype=np.float64).reshape(-1, frequencies)
    residual = np.asarray(residual_m, dtype=np.float64).reshape(-1, frequencies)
    if amplitude.shape != residual.shape:
        raise ValueError(f"amplitude {amplitude.shape} and residual_m {residual.shape} must have the same shape")
    lever = np.zeros(amplitude.shape[0]) if leverage is None else np.asarray(leverage, dtype=np.float64).ravel()
    if lever.shape != (amplitude.shape[0],):
        raise ValueError(f"leverage must have one value per row ({amplitude.shape[0]}), got {lever.shape}")
    with np.errstate(invalid="ignore"):
        good = (np.isfinite(residual).all(1) & np.isfinite(amplitude).all(1) & (amplitude > 0).all(1)
                & np.isfinite(lever) & (lever >= 0) & (lever < 1))
    rows = np.flatnonzero(good)
    if rows.size > MAX_PIXELS:  # evenly spaced, so every part of the scan keeps its share
        rows = rows[np.linspace(0, rows.size - 1, MAX_PIXELS).round().astype(np.intp)]
    return amplitude[rows], residual[rows], lever[rows]


def _decades(amplitude: NDArray) -> float:
    """log10 of the 95th over the 5th percentile of all amplitudes (n, F). [1]"""
    low, high = np.percentile(amplitude, [5, 95])
    return float(np.log10(high / low))


@lru_cache(maxsize=8)
def gaussian_t_scale(dof: float) -> float:
    """The scale k of the Student-t of ``dof`` degrees of freedom that maximum likelihood fits to Gaussian noise of
    unit standard deviation. [1]

    k solves E_z[(nu + 1) z^2 / (nu k^2 + z^2)] = 1 for z ~ N(0, 1), the t's scale score at zero; the expectation
    is a Gauss-Hermite sum.
    """
    from scipy.optimize import brentq

    nodes, weights = np.polynomial.hermite_e.hermegauss(120)
    weights = weights / weights.sum()

    def score(k: float) -> float:
        return float(weights @ ((dof + 1) * nodes**2 / (dof * k**2 + nodes**2))) - 1.0

    return float(brentq(score, 0.1, 10.0, xtol=1e-14))


class _NoiseTable:
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
class _Likelihood:
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
    table: _NoiseTable = field(init=False)
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
        self.table = _NoiseTable(self.sensor, self.frequencies_hz, float(self.log_amplitude.min()) - high,
                                 float(self.log_amplitude.max()) - low)
        spread = 1.4826 * np.median(np.abs(self.residual - np.median(self.residual, axis=0)), axis=0)
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


def _result(model: _Likelihood, theta: NDArray, covariance: NDArray, converged: bool, reference: int,
            decades: float, pixels: int, outliers: int) -> SensorScale:
    """The :class:`SensorScale` of a fit: estimates, standard deviations, and whether they are significant."""
    log_scale, log_noise, offsets = model.split(theta)
    frequencies = offsets.size
    first_offset = 2 if model.fits_noise else 1
    # Offsets relative to the reference (highest) frequency: difference vectors through the covariance.
    contrast = np.zeros((frequencies, theta.size))
    contrast[:, first_offset:first_offset + frequencies] = np.diag(model.unit_m)
    contrast[:, first_offset + reference] -= model.unit_m[reference]
    offset_variance = np.einsum("ij,jk,ik->i", contrast, covariance, contrast)
    scale_sd = float(np.sqrt(covariance[0, 0]))
    noise_sd = float(np.sqrt(covariance[1, 1])) if model.fits_noise else 0.0
    correlation = float("nan")
    if model.fits_noise and np.isfinite(scale_sd * noise_sd) and scale_sd * noise_sd > 0:
        correlation = float(covariance[0, 1] / (scale_sd * noise_sd))
    at_bound = abs(log_scale - model.bounds[0][0]) < 1e-3 or abs(log_scale - model.bounds[0][1]) < 1e-3
    if at_bound:  # the likelihood still rises beyond the searched range: the scale is not determined
        scale_sd = float("inf")
    reason = _reason(model, theta, covariance, converged, at_bound, scale_sd, noise_sd, decades)
    return SensorScale(
        amplitude_scale=float(np.exp(log_scale)), amplitude_scale_sigma=float(np.exp(log_scale) * scale_sd),
        noise_scale=float(np.exp(log_noise)), noise_scale_sigma=float(np.exp(log_noise) * noise_sd),
        offsets_m=offsets - offsets[reference], offsets_sigma_m=np.sqrt(np.maximum(offset_variance, 0.0)),
        pixels=pixels, significant=not reason, reason=reason, scale_noise_correlation=correlation,
        amplitude_decades=decades, outliers=outliers)


def _reason(model: _Likelihood, theta: NDArray, covariance: NDArray, converged: bool, at_bound: bool,
            scale_sd: float, noise_sd: float, decades: float) -> str:
    """Why a fit is not significant ("" where it is)."""
    if not converged:
        return "the likelihood fit did not converge"
    if scale_sd <= MAX_RELATIVE_SIGMA and noise_sd <= MAX_RELATIVE_SIGMA:
        return ""
    span = f"the flat pixels' amplitudes span {decades:.2f} decades (5-95 %)"
    if model.fits_noise and at_bound:
        return (f"{span}: the likelihood keeps rising to the edge of the searched amplitude scales, so only a "
                "product of amplitude scale and noise scale is determined; fix the noise scale (fix_noise_scale=1) "
                "to read the amplitude scale")
    if model.fits_noise and np.isfinite(covariance[:2, :2]).all():
        power, product_sd = _best_determined_product(covariance)
        if product_sd <= MAX_RELATIVE_SIGMA:
            product = float(np.exp(power * theta[0] + theta[1]))
            return (f"{span}, too narrow to tell the amplitude scale from the noise scale (relative sigmas "
                    f"{scale_sd:.2g} and {noise_sd:.2g}): only amplitude_scale^{power:.2f} x noise_scale is "
                    f"determined, {product:.4g} to {product_sd:.2g}; fix the noise scale (fix_noise_scale=1) to read "
                    "the amplitude scale")
    return (f"the amplitude scale is known only to {scale_sd:.2g} (relative sigma; noise scale {noise_sd:.2g}), "
            f"more than {MAX_RELATIVE_SIGMA:g}: too few or too noisy flat pixels, or {span}")


def _best_determined_product(covariance: NDArray) -> tuple[float, float]:
    """The power p of lambda^p eta best determined by the fit, and that product's relative standard deviation.

    Var(p log lambda + log eta) = p^2 V_ll + 2 p V_le + V_ee is least at p = -V_le / V_ll: p = 1 where the noise is
    thermal (sd ~ lambda eta / A), 1/2 where it is shot noise (sd ~ eta sqrt(lambda / A)).
    """
    v_ll, v_le, v_ee = covariance[0, 0], covariance[0, 1], covariance[1, 1]
    power = -v_le / v_ll
    return float(power), float(np.sqrt(max(v_ee - v_le**2 / v_ll, 0.0)))


def _nothing_measured(frequencies: int, pixels: int, fix_noise_scale: float | None, reason: str) -> SensorScale:
    """The :class:`SensorScale` of too few pixels: NaN estimates, infinite standard deviations."""
    return SensorScale(
        amplitude_scale=float("nan"), amplitude_scale_sigma=float("inf"),
        noise_scale=float("nan") if fix_noise_scale is None else float(fix_noise_scale),
        noise_scale_sigma=float("inf") if fix_noise_scale is None else 0.0,
        offsets_m=np.full(frequencies, np.nan), offsets_sigma_m=np.full(frequencies, np.inf), pixels=pixels,
        significant=False, reason=reason)


# --- residuals from a scan's flat surfaces ------------------------------------------------------------------


def flat_surface_residuals(scan: Scan, usable_depth: NDArray, options: CorrectionOptions, *,
                           scene: SceneGeometry | None = None, max_pixels: int = MAX_PIXELS,
                           window_sensor: SensorConfig | None = None) -> FlatSurfaceResiduals:
    """Each frequency's depth minus its block's plane, on the inner blocks of the scan's flat surfaces that no
    surface faces.

    A block is taken when it and its eight neighbours lie on one flat surface
    (:func:`~mpi_lidar.correction.footprint.surface_labels`: no depth edge, no bend within a block of it), none
    of them has a multipath bias above ``MAX_FLAT_BIAS_M`` at a generous footprint (``GENEROUS_FOOTPRINT_FACTOR``
    times the default effective footprint, or the given one if larger), and its own plane kept ``MIN_KEPT_SHARE``
    of its pixels. Each taken block's plane is fitted again, to the mean depth over the frequencies
    (:func:`mpi_lidar.scans.geometry.fit_block_planes`, its robust fit). A pixel of the block gets residuals when
    its depth is usable, no neighbour of it is off its own block's plane (an edge's mixed pixels) and its mean depth
    lies within ``PLANE_WINDOW_SIGMAS`` of the plane: the pixels the fit trimmed count too, so that no frequency's
    residuals are truncated.

    Multipath from surfaces beyond ``options.partner_range_m`` is not seen (the blocks pair only within it): on the
    far halves of a 90-degree corner of 1.2 m boards it leaves the pixels taken a bias of up to 1 mm, 0.1 mm on
    average between frequencies, which reads as part of the depth offsets and is far below the noise the scales are
    measured on.

    Parameters
    ----------
    scan : Scan
        The scan (its maps may stay in the store).
    usable_depth : NDArray
        Highest-frequency depth (H*W,) of the usable pixels, NaN elsewhere. [m] Where the amplitude's units are not
        known, make it from the depths alone (finite, frequencies consistent): amplitude thresholds in V^2 would
        take a scan in other units for saturated or dark.
    options : CorrectionOptions
        Block size, partner range, footprint and tile size of the scene geometry.
    scene : SceneGeometry | None
        The scan's scene geometry where it was analysed already (its blocks and surfaces are used).
    max_pixels : int
        At most this many pixels: whole blocks, evenly spaced among those taken.
    window_sensor : SensorConfig | None
        Where given, each frequency's depth has this sensor's integration window's leakage removed first.

    Returns
    -------
    FlatSurfaceResiduals
        Amplitudes, residuals, leverages and pixel indices; none for a scan without geometry or flat surfaces.
    """
    frequencies = len(scan.frequencies_hz)
    blocks = scene.blocks if scene is not None and scene.blocks is not None else scene_blocks(scan, usable_depth,
                                                                                               options)
    if blocks is None:
        return _no_residuals(frequencies)
    labels = scene.surfaces if scene is not None and scene.surfaces is not None else surface_labels(blocks)
    chosen = np.flatnonzero(_quiet_inner_blocks(blocks, labels.flat, options))
    per_block = blocks.block_pixels**2
    if chosen.size * per_block > max_pixels:  # evenly spaced whole blocks, so every surface keeps its share
        keep = max(1, max_pixels // per_block)
        chosen = chosen[np.linspace(0, chosen.size - 1, keep).round().astype(np.intp)]
    if chosen.size == 0:
        return _no_residuals(frequencies)
    return _block_residuals(scan, usable_depth, blocks, chosen, window_sensor)


def _no_residuals(frequencies: int) -> FlatSurfaceResiduals:
    return FlatSurfaceResiduals(np.zeros((0, frequencies)), np.zeros((0, frequencies)), np.zeros(0),
                                np.zeros(0, dtype=np.intp))


def _quiet_inner_blocks(blocks: geometry.FacingBlocks, flat: NDArray, options: CorrectionOptions) -> NDArray:
    """Blocks (Hb*Wb,) that lie with their eight neighbours on one flat surface, none of the nine reaching a
    multipath bias of ``MAX_FLAT_BIAS_M`` at a generous footprint, whose plane kept ``MIN_KEPT_SHARE`` of its
    pixels.

    Pixels interpolate block values from the neighbouring blocks, so a block is as quiet as its neighbourhood;
    past the scan's border a block is its own neighbour.
    """
    hb, wb = blocks.usable.shape
    labels = flat.reshape(hb, wb)
    padded = np.pad(labels, 1, mode="edge")
    inner = labels >= 0
    for dy in (-1, 0, 1):
        for dx in (-1, 0, 1):
            inner &= padded[1 + dy:1 + dy + hb, 1 + dx:1 + dx + wb] == labels
    given = 0.0 if options.footprint_area_m2 == AUTO else float(options.footprint_area_m2)
    footprint_m2 = max(given, GENEROUS_FOOTPRINT_FACTOR * DEFAULT_FOOTPRINT_AREA_M2)
    bias_m = blocks.block_potential(footprint_m2).bias_m.reshape(hb, wb)
    quiet = _neighbourhood_max(bias_m) <= MAX_FLAT_BIAS_M
    finite = np.nansum(geometry.to_blocks(blocks.finite.astype(np.float64), blocks.block_pixels), axis=-1)
    whole = blocks.keep.sum(-1) >= MIN_KEPT_SHARE * finite
    return (inner & quiet & whole).ravel()


# The eight neighbours of a cell (row step, column step).
_NEIGHBOURS = tuple((dy, dx) for dy in (-1, 0, 1) for dx in (-1, 0, 1) if (dy, dx) != (0, 0))


def _neighbourhood_max(values: NDArray) -> NDArray:
    """Each cell's largest value over itself and its eight neighbours (2-D), a cell past the border being the
    nearest one on it; NaN where any of the nine is NaN."""
    h, w = values.shape
    padded = np.pad(values, 1, mode="edge")
    largest = values.copy()
    for dy, dx in _NEIGHBOURS:
        np.maximum(largest, padded[1 + dy:1 + dy + h, 1 + dx:1 + dx + w], out=largest)
    return largest


def _any_neighbour(mask: NDArray[np.bool_]) -> NDArray[np.bool_]:
    """Cells (2-D) with one of their eight neighbours set in ``mask``; past the border there is no neighbour."""
    h, w = mask.shape
    padded = np.pad(mask, 1, constant_values=False)
    found = np.zeros_like(mask)
    for dy, dx in _NEIGHBOURS:
        found |= padded[1 + dy:1 + dy + h, 1 + dx:1 + dx + w]
    return found


def _block_residuals(scan: Scan, usable_depth: NDArray, blocks: geometry.FacingBlocks,
                     chosen: NDArray, window_sensor: SensorConfig | None = None) -> FlatSurfaceResiduals:
    """Residuals of the pixels of the blocks ``chosen`` (K,) (flat block indices) from planes fitted to their mean
    depth over the frequencies; only pixels whose mean depth lies within ``PLANE_WINDOW_SIGMAS`` of the plane.
    With ``window_sensor``, of the depths less that sensor's window leakage."""
    b = blocks.block_pixels
    pixels = _pixels_of_blocks(blocks, chosen)
    present = np.flatnonzero(pixels >= 0)
    y, x = np.divmod(pixels[present], blocks.shape[1])
    depth = np.full((pixels.size, len(scan.frequencies_hz)), np.nan)
    depth[present] = np.asarray(scan.depth[:, y, x], dtype=np.float64).T
    amplitude = np.full_like(depth, np.nan)
    amplitude[present] = np.asarray(scan.amplitude[:, y, x], dtype=np.float64).T
    if window_sensor is not None:
        depth[present] += window_corrections_m(depth[present], amplitude[present], scan.frequencies_hz, window_sensor)
    rays = np.full((pixels.size, 3), np.nan)
    rays[present] = scan.pixel_rays(y, x)
    usable = np.zeros(pixels.size, dtype=bool)
    usable[present] = (np.isfinite(np.asarray(usable_depth).reshape(-1)[pixels[present]])
                       & ~_beside_other_surfaces(blocks).reshape(-1)[pixels[present]])
    usable &= np.isfinite(depth).all(1) & np.isfinite(amplitude).all(1)
    mean_depth = np.where(usable, depth.mean(1), np.nan)
    plane_depth, fitted = _mean_depth_planes(mean_depth, rays, chosen.size, b)
    with np.errstate(invalid="ignore"):  # pixels without a depth or a plane
        off_plane = np.abs(mean_depth - plane_depth).reshape(chosen.size, b * b)
        spread = 1.4826 * geometry.nanmedian_last(np.where(fitted, off_plane, np.nan))
        near = (off_plane <= PLANE_WINDOW_SIGMAS * spread[:, None]).reshape(-1)
    leverage = _plane_leverage(fitted, b).reshape(-1)
    take = usable & near & np.isfinite(plane_depth) & np.isfinite(leverage)
    return FlatSurfaceResiduals(amplitude[take], depth[take] - plane_depth[take, None], leverage[take],
                                pixels[take].astype(np.intp), int(np.unique(np.flatnonzero(take) // (b * b)).size))


def _beside_other_surfaces(blocks: geometry.FacingBlocks) -> NDArray[np.bool_]:
    """Pixels (H, W) with one of their eight neighbours off its block's plane or without a depth: next to a depth
    edge, where a real scan's pixels mix two surfaces.

    A pixel's own distance from the plane does not count, so that the pixels the fit trimmed for their noise keep
    their residuals, and their neighbours, left out for it, are left out whatever their own noise.
    """
    hb, wb = blocks.usable.shape
    b = blocks.block_pixels
    height, width = blocks.shape
    inlier = blocks.keep.reshape(hb, wb, b, b).swapaxes(1, 2).reshape(hb * b, wb * b)[:height, :width]
    return _any_neighbour(~inlier)


def _pixels_of_blocks(blocks: geometry.FacingBlocks, chosen: NDArray) -> NDArray[np.intp]:
    """Flat pixel indices (K b b,) of the blocks ``chosen`` (K,), block by block, each row by row; -1 past the
    scan's edge."""
    b = blocks.block_pixels
    height, width = blocks.shape
    block_row, block_column = np.divmod(chosen, blocks.usable.shape[1])
    ys = np.broadcast_to(block_row[:, None, None] * b + np.arange(b)[None, :, None], (chosen.size, b, b))
    xs = np.broadcast_to(block_column[:, None, None] * b + np.arange(b)[None, None, :], (chosen.size, b, b))
    return np.where((ys < height) & (xs < width), ys * width + xs, -1).reshape(-1)


def _mean_depth_planes(mean_depth: NDArray, rays: NDArray, count: int, b: int) -> tuple[NDArray, NDArray]:
    """The plane's depth along each pixel's ray (K b b,) [m] from the robust plane of each of K blocks' mean
    depths (K b b,) [m] along their rays (K b b, 3), and the pixels the fit kept (K, b*b).

    The blocks are laid side by side in a grid of b rows and K b columns, so that one call of
    :func:`~mpi_lidar.scans.geometry.fit_block_planes` fits them all; NaN where a block has no plane.
    """
    # (K, b, b, 3) -> (b, K b, 3): block k's pixel (row, column) at grid (row, k b + column).
    points = (mean_depth[:, None] * rays).reshape(count, b, b, 3).swapaxes(0, 1).reshape(b, count * b, 3)
    with np.errstate(invalid="ignore", divide="ignore"):  # blocks left without points
        centres, normals, keep, usable, _ = geometry.fit_block_planes(points, b)
        block_of = np.repeat(np.arange(count), b * b)
        plane_depth = (np.einsum("ki,ki->k", normals[0], centres[0])[block_of]
                       / np.einsum("ni,ni->n", normals[0][block_of], rays))
    plane_depth[~usable[0][block_of]] = np.nan
    return plane_depth, keep[0] & usable[0][:, None]


def _plane_leverage(fitted: NDArray, b: int) -> NDArray[np.float64]:
    """Leverage (K, b*b) of each pixel of K blocks in a least-squares plane over the pixels ``fitted`` (K, b*b).

    The plane is linear in the pixel's row and column within a block (the ray's angles, to first order), and a
    leverage does not change under an affine change of the regressors: h = x^T (X^T X)^-1 x with x = (1, row,
    column) and X the fitted pixels' rows. The few pixels the robust fit trimmed get the same x^T (X^T X)^-1 x, the
    leverage of a prediction: (S1) understates their variance by 2 h s_f^2 / F, a negligible error on so few.
    """
    row, column = np.divmod(np.arange(b * b), b)
    x = np.column_stack([np.ones(b * b), row, column]).astype(np.float64)  # (b*b, 3)
    weight = fitted.astype(np.float64)
    gram = np.einsum("kn,ni,nj->kij", weight, x, x)  # X^T X per block (K, 3, 3)
    # A block with fewer than three pixels in a line has a singular Gram matrix: no leverage, and no residuals.
    singular = np.linalg.matrix_rank(gram) < 3
    gram[singular] = np.eye(3)
    inverse = np.linalg.inv(gram)
    leverage = np.einsum("ni,kij,nj->kn", x, inverse, x)
    leverage[singular] = np.nan
    return leverage
