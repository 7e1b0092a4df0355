"""A resolved pixel's two ranges' 1-sigma (:func:`range_sigmas`): the two-return fit's Cramer-Rao bound.

Two returns are four parameters, the ranges d_1, d_2 and the real amplitudes a_1, a_2, seen through 2F real numbers
(each frequency's phasor z_k, its real and imaginary part with the quadrature noise sigma_k each). The Fisher
information is J^T J of the noise-weighted Jacobian,

.. math::

    \\partial z_k / \\partial d_j = i w_k a_j e^{i w_k d_j}, \\quad
    \\partial z_k / \\partial a_j = e^{i w_k d_j}, \\quad w_k = 4 \\pi f_k / c,

and a range's 1-sigma is the square root of its diagonal entry of the inverse: the covariance of the weighted
least-squares fit at its optimum, which it reaches where the noise is small against the returns. The amplitudes
being unknown, and the two returns' columns far from orthogonal over four frequencies, a range's sigma is several
times one return's of the same light; the weaker return's the larger.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

from mpi_lidar.physics.noise import NoiseModel
from mpi_lidar.physics.two_returns import TwoReturns, fit_two_returns


def range_sigmas(near_m: ArrayLike, far_m: ArrayLike, near_amplitude: ArrayLike, far_amplitude: ArrayLike,
                 frequencies_hz: ArrayLike, quadrature_sigma_v2: ArrayLike, c: float) -> NDArray[np.float64]:
    """The Cramer-Rao bound (n, 2) of the nearer and the farther range [m] of two returns.

    Parameters
    ----------
    near_m, far_m : The two returns' ranges (n,). [m]
    near_amplitude, far_amplitude : Their amplitudes (n,). [V^2]
    frequencies_hz : The frequencies (F,). [Hz]
    quadrature_sigma_v2 : The noise of each phasor's real and imaginary part (n, F). [V^2]
    c : The speed of light. [m/s]

    NaN where a parameter is not finite or the information is singular (a return of no light).
    """
    near, far = (np.atleast_1d(np.asarray(v, dtype=np.float64)) for v in (near_m, far_m))
    a_near, a_far = (np.atleast_1d(np.asarray(v, dtype=np.float64)) for v in (near_amplitude, far_amplitude))
    w = 4 * np.pi * np.asarray(frequencies_hz, dtype=np.float64) / c
    sigma = np.broadcast_to(np.asarray(quadrature_sigma_v2, dtype=np.float64), (near.size, w.size))
    out = np.full((near.size, 2), np.nan)
    usable = np.flatnonzero(np.isfinite(near) & np.isfinite(far) & (a_near > 0) & (a_far > 0)
                            & np.isfinite(sigma).all(axis=1) & (sigma > 0).all(axis=1))
    if not usable.size:
        return out
    e1 = np.exp(1j * near[usable, None] * w) / sigma[usable]
    e2 = np.exp(1j * far[usable, None] * w) / sigma[usable]
    columns = (1j * w * a_near[usable, None] * e1, 1j * w * a_far[usable, None] * e2, e1, e2)
    jacobian = np.stack([np.concatenate([col.real, col.imag], axis=1) for col in columns], axis=-1)  # (k, 2F, 4)
    fisher = np.einsum("kfi,kfj->kij", jacobian, jacobian)
    with np.errstate(invalid="ignore", divide="ignore"):
        determinant = np.linalg.det(fisher)
        regular = determinant > 0
        variance = np.full((usable.size, 2), np.nan)
        if regular.any():
            variance[regular] = np.diagonal(np.linalg.inv(fisher[regular]), axis1=1, axis2=2)[:, :2]
    out[usable] = np.sqrt(np.where(variance > 0, variance, np.nan))
    return out


def stronger_and_weaker_sigmas(fit: TwoReturns, frequencies_hz: ArrayLike, quadrature_sigma_v2: ArrayLike,
                               c: float) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """The 1-sigma (n,) [m] of the stronger and of the weaker return's range of two-return fits ``fit``, with the
    phasors' quadrature noise (n, F) [V^2] at ``frequencies_hz`` (F,) [Hz] and the speed of light ``c`` [m/s]."""
    both = range_sigmas(fit.near_m, fit.far_m, fit.near_amplitude, fit.far_amplitude, frequencies_hz,
                        quadrature_sigma_v2, c)
    near_stronger = fit.near_amplitude >= fit.far_amplitude  # as TwoReturns.stronger_m takes it
    return np.where(near_stronger, both[:, 0], both[:, 1]), np.where(near_stronger, both[:, 1], both[:, 0])


def fit_with_sigmas(rows: NDArray, depth_m: NDArray, noise: NoiseModel,
                    ) -> tuple[TwoReturns, NDArray[np.float64], NDArray[np.float64]]:
    """Two returns fitted to raw rows (k, 2F) [m, V^2] about their measured depths (k,) [m]
    (:func:`~mpi_lidar.physics.two_returns.fit_two_returns`, weighed by ``noise``'s quadrature sd of the rows'
    amplitudes), with the stronger and the weaker return's 1-sigma (k,) [m] (:func:`range_sigmas`). The mixed-pixel
    stage resolves its pixels with it and the per-pixel estimate reads the stronger's sigma from it again: the same
    rows give the same fit."""
    f = len(noise.frequencies_hz)
    sigma = noise.quadrature_sigma_v2(rows[:, f:].astype(np.float64))
    fit = fit_two_returns(rows, noise.frequencies_hz, sigma, noise.speed_of_light_m_per_s, depth_m)
    stronger, weaker = stronger_and_weaker_sigmas(fit, noise.frequencies_hz, sigma, noise.speed_of_light_m_per_s)
    return fit, stronger, weaker
