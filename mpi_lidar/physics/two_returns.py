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

:func:`fit_two_returns` also weighs the fit by the noise: chi^2 of its phasor residual in units of each
frequency's quadrature noise, chi^2(2F - 4) where two returns are what the pixel saw.
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


def fit_two_returns(raw: ArrayLike, frequencies_hz: ArrayLike, quadrature_sigma_v2: ArrayLike, c: float,
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
    model = model_phasors(near, offset, near_amplitude, far_amplitude, freqs, c)
    sigma = np.maximum(np.asarray(quadrature_sigma_v2, dtype=np.float64), 1e-300)
    chi2 = (np.abs(model - measured_phasors(rows, freqs, c)) ** 2 / sigma**2).sum(axis=1)
    ok = (fit.status == FIT_OK) & np.isfinite(chi2)
    nan = np.full(rows.shape[0], np.nan)
    return TwoReturns(np.where(ok, near, nan), np.where(ok, near + offset, nan), np.where(ok, near_amplitude, nan),
                      np.where(ok, far_amplitude, nan), np.where(ok, chi2, np.inf))
