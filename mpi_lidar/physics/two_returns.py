"""Two surfaces in one footprint: a pixel straddling a depth edge sees two returns, and its phasor at each
frequency is their sum,

    z_k = a_1 exp(+i w_k d_1) + a_2 exp(+i w_k d_2),    w_k = 4 pi f_k / c,

with real amplitudes a_1, a_2 >= 0 the same at every frequency. At equally spaced frequencies (f_k = f_0 + k df)
z_k is a sum of two exponentials in k, so a two-pole Prony / matrix-pencil fit gives both poles in closed form,
exp(+i 4 pi df d / c), unambiguous to c / (2 df) (24 m at 6.25 MHz), and a bounded least-squares fit refines them
(:func:`mpi_lidar.physics.inverse.prony_two_path`, :func:`~mpi_lidar.physics.inverse.least_squares_two_path`, with
no bound on the gap below that ambiguity nor on the amplitude ratio). The two returns' phasors turn apart by
4 pi df / c, about 0.26 rad per metre of gap, across the four frequencies: below a metre or two the poles are too
close for four noisy samples to tell, and one blurred return fits about as well.

At other frequency sets there are no poles: :func:`least_squares_two_returns` fits the same model by weighted
least squares, from the best pair of ranges on a grid (the amplitudes of each pair follow in closed form, the model
being linear in them), refined by Levenberg-Marquardt; on evenly spaced sets it reaches the closed form's fit.
:func:`fit_two_returns` takes the closed form where it can, the least squares elsewhere.

Every fit is weighed by the noise: chi^2 of its phasor residual in units of each frequency's quadrature noise,
chi^2(2F - 4) where two returns are what the pixel saw.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from mpi_lidar.physics.inverse import (
    FIT_OK,
    frequency_step,
    least_squares_two_path,
    measured_phasors,
    model_phasors,
    prony_two_path,
)

# The largest amplitude ratio of the farther return over the nearer a fit may take: a dark plate before a bright
# wall at twice its range is about 20 times weaker, and the fit needs a bound.
MAX_AMPLITUDE_RATIO = 1e3
SEARCH_M = 12.0  # the least-squares fit seeks both returns within this distance of the pixel's depth [m]
GRID_STEPS_PER_WRAP = 16  # grid steps per wrap of the highest frequency: the cost's basins are wider
GRID_CHUNK_ROWS = 256  # rows whose grid of range pairs is held at a time (about 81 x 81 pairs a row)
REFINE_ITERATIONS = 50


@dataclass(frozen=True)
class TwoReturns:
    """Two-return fits of n pixels; arrays (n,).

    near_m, far_m : The nearer and the farther return's range (NaN where the fit failed). [m]
    near_amplitude, far_amplitude : Their amplitudes (NaN where the fit failed). [V^2]
    chi2 : The fit's phasor residual in units of the quadrature noise (inf where the fit failed). [1]
    """

    near_m: NDArray[np.float64]
    far_m: NDArray[np.float64]
    near_amplitude: NDArray[np.float64]
    far_amplitude: NDArray[np.float64]
    chi2: NDArray[np.float64]

    @property
    def stronger_m(self) -> NDArray[np.float64]:
        """The range of the return with the larger amplitude. [m]"""
        return np.where(self.near_amplitude >= self.far_amplitude, self.near_m, self.far_m)

    @property
    def weaker_m(self) -> NDArray[np.float64]:
        """The range of the return with the smaller amplitude. [m]"""
        return np.where(self.near_amplitude >= self.far_amplitude, self.far_m, self.near_m)

    @property
    def weaker_share(self) -> NDArray[np.float64]:
        """The weaker return's share of the two amplitudes' sum. [1]"""
        with np.errstate(invalid="ignore", divide="ignore"):
            return np.minimum(self.near_amplitude, self.far_amplitude) / (self.near_amplitude + self.far_amplitude)


def evenly_spaced(frequencies_hz: ArrayLike) -> bool:
    """Whether the frequencies are at least four, increasing and evenly spaced: what the closed form needs."""
    freqs = np.asarray(frequencies_hz, dtype=np.float64)
    if freqs.ndim != 1 or freqs.size < 4:
        return False
    steps = np.diff(freqs)
    return bool(steps[0] > 0 and np.allclose(steps, steps[0], rtol=1e-9, atol=0))


def gap_ambiguity_m(frequencies_hz: ArrayLike, c: float) -> float:
    """The distance [m] past which two returns' ranges repeat: c / (2 df) for evenly spaced frequencies (the
    poles'), else c / (2 g) with g the frequencies' greatest common divisor in whole hertz."""
    freqs = np.asarray(frequencies_hz, dtype=np.float64)
    if evenly_spaced(freqs):
        return c / (2 * frequency_step(freqs))
    return c / (2 * float(np.gcd.reduce(np.rint(freqs).astype(np.int64))))


def fit_two_returns(raw: ArrayLike, frequencies_hz: ArrayLike, quadrature_sigma_v2: ArrayLike, c: float,
                    near_m: ArrayLike | None = None) -> TwoReturns:
    """Two returns of raw rows (n, 2F) [m, V^2]: in closed form at evenly spaced frequencies
    (:func:`closed_form_two_returns`), by least squares at any other set of four or more
    (:func:`least_squares_two_returns`). Parameters as those functions take them."""
    if evenly_spaced(frequencies_hz):
        return closed_form_two_returns(raw, frequencies_hz, quadrature_sigma_v2, c, near_m)
    return least_squares_two_returns(raw, frequencies_hz, quadrature_sigma_v2, c, near_m)


def closed_form_two_returns(raw: ArrayLike, frequencies_hz: ArrayLike, quadrature_sigma_v2: ArrayLike, c: float,
                            near_m: ArrayLike | None = None) -> TwoReturns:
    """Two returns of raw rows (n, 2F) [m, V^2] at evenly spaced frequencies (:func:`evenly_spaced`).

    Parameters
    ----------
    raw : Each frequency's depth (wrapped or not: only its phase counts), then its amplitude. [m, V^2]
    frequencies_hz : The frequencies (F,), evenly spaced. [Hz]
    quadrature_sigma_v2 : The noise of each phasor's real and imaginary part (n, F). [V^2]
    c : The speed of light the depths were converted with. [m/s]
    near_m : A depth near the returns (n,), for ranges past c / (2 df): the nearer return is put within half
        that ambiguity of it (None: in [0, c / (2 df))). [m]

    The gap between the returns is taken below half the ambiguity (12 m at 6.25 MHz): the poles cannot tell a
    gap g from c / (2 df) - g with the returns swapped.
    """
    freqs = np.asarray(frequencies_hz, dtype=np.float64)
    rows = np.asarray(raw, dtype=np.float64)
    period = c / (2 * frequency_step(freqs))
    start = prony_two_path(rows, freqs, max_offset_m=period, max_ratio=MAX_AMPLITUDE_RATIO, c=c)
    fit = least_squares_two_path(rows, freqs, start, max_offset_m=period, max_ratio=MAX_AMPLITUDE_RATIO, c=c)
    # The poles tell each range modulo the ambiguity: of the two ways to pair them, the smaller gap is taken.
    wrapped = fit.path_offset_m > period / 2
    near = np.where(wrapped, fit.direct_depth_m + fit.path_offset_m - period, fit.direct_depth_m)
    offset = np.where(wrapped, period - fit.path_offset_m, fit.path_offset_m)
    near_amplitude = np.where(wrapped, fit.multipath_amplitude, fit.direct_amplitude)
    far_amplitude = np.where(wrapped, fit.direct_amplitude, fit.multipath_amplitude)
    if near_m is not None:
        near = near + np.round((np.asarray(near_m, dtype=np.float64) - near) / period) * period
    return _scored(rows, freqs, quadrature_sigma_v2, c, near, near + offset, near_amplitude, far_amplitude,
                   fit.status == FIT_OK)


def _scored(rows: NDArray, freqs: NDArray, quadrature_sigma_v2: ArrayLike, c: float, near: NDArray, far: NDArray,
            near_amplitude: NDArray, far_amplitude: NDArray, ok: NDArray) -> TwoReturns:
    """The fits with their chi^2 in units of the quadrature noise, NaN (chi^2 inf) where not ``ok``."""
    model = model_phasors(near, far - near, near_amplitude, far_amplitude, freqs, c)
    sigma = np.maximum(np.asarray(quadrature_sigma_v2, dtype=np.float64), 1e-300)
    chi2 = (np.abs(model - measured_phasors(rows, freqs, c)) ** 2 / sigma**2).sum(axis=1)
    ok = ok & np.isfinite(chi2)
    nan = np.full(rows.shape[0], np.nan)
    return TwoReturns(np.where(ok, near, nan), np.where(ok, far, nan), np.where(ok, near_amplitude, nan),
                      np.where(ok, far_amplitude, nan), np.where(ok, chi2, np.inf))


def least_squares_two_returns(raw: ArrayLike, frequencies_hz: ArrayLike, quadrature_sigma_v2: ArrayLike, c: float,
                              near_m: ArrayLike | None = None) -> TwoReturns:
    """Two returns of raw rows (n, 2F) [m, V^2] at any four or more frequencies, by weighted least squares.

    The model is linear in the two amplitudes, so for every pair of ranges on a grid (``GRID_STEPS_PER_WRAP``
    steps per wrap of the highest frequency, within ``SEARCH_M`` of ``near_m``) they follow in closed form, and
    the pair that explains most of the phasors' power, both amplitudes non-negative, starts a damped Gauss-Newton
    refinement of all four parameters (:func:`_refined`). Every phasor is weighed by its quadrature noise.

    Parameters
    ----------
    raw : Each frequency's depth (wrapped or not: only its phase counts), then its amplitude. [m, V^2]
    frequencies_hz : The frequencies (F,), F >= 4, in any order and spacing. [Hz]
    quadrature_sigma_v2 : The noise of each phasor's real and imaginary part (n, F). [V^2]
    c : The speed of light the depths were converted with. [m/s]
    near_m : A depth between or near the returns (n,): both are sought within ``SEARCH_M`` of it (None: within
        [0, 2 ``SEARCH_M``]). [m]
    """
    freqs = np.asarray(frequencies_hz, dtype=np.float64)
    rows = np.asarray(raw, dtype=np.float64)
    n = rows.shape[0]
    sigma = np.maximum(np.broadcast_to(np.asarray(quadrature_sigma_v2, dtype=np.float64), (n, freqs.size)), 1e-300)
    weighted = measured_phasors(rows, freqs, c) / sigma
    centre = np.full(n, SEARCH_M) if near_m is None else np.asarray(near_m, dtype=np.float64)
    lowest = np.maximum(np.nan_to_num(centre, nan=SEARCH_M) - SEARCH_M, 0.0)
    step = c / (2 * freqs.max()) / GRID_STEPS_PER_WRAP
    grid = lowest[:, None] + step * np.arange(int(np.ceil(2 * SEARCH_M / step)) + 1)  # (n, G)
    w = 4 * np.pi * freqs / c
    start = np.full((n, 4), np.nan)
    for chunk in range(0, n, GRID_CHUNK_ROWS):
        part = slice(chunk, min(chunk + GRID_CHUNK_ROWS, n))
        start[part] = _grid_start(weighted[part], sigma[part], grid[part], w)
    p, converged = _refined(weighted, sigma, w, start)
    order = p[:, 0] <= p[:, 1]
    near, far = np.where(order, p[:, 0], p[:, 1]), np.where(order, p[:, 1], p[:, 0])
    near_amplitude, far_amplitude = np.where(order, p[:, 2], p[:, 3]), np.where(order, p[:, 3], p[:, 2])
    ok = converged & np.isfinite(p).all(axis=1) & (near_amplitude > 0) & (far_amplitude > 0) & (far > near)
    return _scored(rows, freqs, sigma, c, near, far, near_amplitude, far_amplitude, ok)



def _grid_start(weighted: NDArray, sigma: NDArray, grid: NDArray, w: NDArray) -> NDArray[np.float64]:
    """(n, 4) near, far range [m] and their amplitudes [V^2]: the grid pair whose non-negative amplitudes explain
    most of the noise-weighted phasors ``weighted`` (n, F) (``sigma`` (n, F), ``grid`` (n, G) [m], ``w`` (F,))."""
    basis = np.exp(1j * grid[:, :, None] * w) / sigma[:, None, :]  # (n, G, F)
    gram = np.einsum("ngf,nhf->ngh", basis.conj(), basis).real  # (n, G, G)
    proj = np.einsum("ngf,nf->ng", basis.conj(), weighted).real  # (n, G)
    diag = np.diagonal(gram, axis1=1, axis2=2)  # (n, G)
    det = diag[:, :, None] * diag[:, None, :] - gram**2
    with np.errstate(invalid="ignore", divide="ignore"):
        first = (diag[:, None, :] * proj[:, :, None] - gram * proj[:, None, :]) / det
        second = (diag[:, :, None] * proj[:, None, :] - gram * proj[:, :, None]) / det
        explained = first * proj[:, :, None] + second * proj[:, None, :]
    upper = np.triu(np.ones(gram.shape[1:], bool), k=1)  # near < far, distinct grid points
    usable = upper & (first > 0) & (second > 0) & (det > 1e-9 * diag[:, :, None] * diag[:, None, :])
    explained = np.where(usable, explained, -np.inf).reshape(grid.shape[0], -1)
    best = np.argmax(explained, axis=1)
    i, j = np.divmod(best, grid.shape[1])
    rows = np.arange(grid.shape[0])
    found = np.isfinite(explained[rows, best])
    out = np.column_stack([grid[rows, i], grid[rows, j], first.reshape(grid.shape[0], -1)[rows, best],
                           second.reshape(grid.shape[0], -1)[rows, best]])
    return np.where(found[:, None], out, np.nan)


def _refined(weighted: NDArray, sigma: NDArray, w: NDArray, start: NDArray) -> tuple[NDArray, NDArray[np.bool_]]:
    """Levenberg-Marquardt on (near, far, a_near, a_far) from ``start`` (n, 4) of the residual
    (model - z) / sigma; returns the parameters (n, 4) and whether each row converged."""
    p = start.copy()
    usable = np.isfinite(p).all(axis=1)
    p[~usable] = 0.0

    def residual_and_jacobian(q: NDArray) -> tuple[NDArray, NDArray]:
        e1, e2 = np.exp(1j * q[:, :1] * w) / sigma, np.exp(1j * q[:, 1:2] * w) / sigma
        res = q[:, 2:3] * e1 + q[:, 3:4] * e2 - weighted
        cols = (1j * w * q[:, 2:3] * e1, 1j * w * q[:, 3:4] * e2, e1, e2)
        jac = np.stack([np.concatenate([col.real, col.imag], axis=1) for col in cols], axis=-1)
        return np.concatenate([res.real, res.imag], axis=1), jac

    res, jac = residual_and_jacobian(p)
    cost = (res**2).sum(axis=1)
    damping = np.full(p.shape[0], 1e-3)
    converged = np.zeros(p.shape[0], bool)
    for _ in range(REFINE_ITERATIONS):
        normal = np.einsum("nki,nkj->nij", jac, jac)
        scale = np.diagonal(normal, axis1=1, axis2=2)
        lhs = normal + (damping[:, None] * (scale + 1e-300))[:, :, None] * np.eye(4)
        with np.errstate(invalid="ignore", over="ignore"):
            step = np.linalg.solve(lhs, -np.einsum("nki,nk->ni", jac, res)[..., None])[..., 0]
        trial = p + np.nan_to_num(step)
        trial[:, 2:] = np.maximum(trial[:, 2:], 0.0)
        res_t, jac_t = residual_and_jacobian(trial)
        cost_t = (res_t**2).sum(axis=1)
        better = cost_t < cost
        converged |= better & (cost - cost_t <= 1e-10 * cost)
        p[better], res[better], jac[better], cost[better] = trial[better], res_t[better], jac_t[better], cost_t[better]
        damping = np.where(better, np.maximum(damping / 3, 1e-12), damping * 4)
        converged |= damping > 1e10  # no step lowers the cost: at a minimum
    return np.where(usable[:, None], p, np.nan), converged & usable
