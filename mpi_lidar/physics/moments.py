"""Moment-matched simulator: the exact mean and covariance of the taps, sampled as a Gaussian.

Each tap is a weighted sum of ~2667 independent bin voltages (eq 4), so it is Gaussian to high accuracy.
Its mean and covariance follow exactly from the per-bin means and variances of the detector chain
(eq 16-30). Since the expected photon count per bin is X0 + Xc cos(w t) + Xs sin(w t) and the per-bin
variance is affine in it, every sum over bins reduces to a handful of trigonometric sums fixed per
frequency, and the cost no longer grows with the number of bins. The only non-affine step, rounding the
photon count (eq 16), is summed bin by bin for the samples whose peak count is low enough for it to matter.

In parallel-phase demodulation C2 = -C0 and C3 = -C1, so the taps live in two dimensions: the in-phase
sum P = C0 and the quadrature sum Q = C3; their 4x4 covariance has rank 2.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

from mpi_lidar.config import Config
from mpi_lidar.physics import demod
from mpi_lidar.physics.sensor import PhotonWaveform, SensorModel

# Rounding shifts a bin's mean by at most half a photon; above this peak count its effect on the phase
# is below 1e-5 rad (< 10 um at 31.25 MHz), so the affine closed form is used there.
EXACT_ROUNDING_BELOW_PHOTONS = 1000.0

# Maps (P, Q) to the four taps (C0, C1, C2, C3) = (P, -Q, -P, Q).
TAPS_FROM_PQ = np.array([[1.0, 0.0], [0.0, -1.0], [-1.0, 0.0], [0.0, 1.0]])


class TrigSums:
    """Sums over the integration window of products of u = cos(w t_i) and v = sin(w t_i)."""

    def __init__(self, wt: NDArray[np.float64]):
        u, v = np.cos(wt), np.sin(wt)
        self.wt, self.u, self.v = wt, u, v
        self.bins = wt.size
        self.su, self.sv = u.sum(), v.sum()
        self.suu, self.suv, self.svv = (u * u).sum(), (u * v).sum(), (v * v).sum()
        self.suuu, self.suuv = (u**3).sum(), (u * u * v).sum()
        self.suvv, self.svvv = (u * v * v).sum(), (v**3).sum()


class MomentSensor(SensorModel):
    """Default simulator: Gaussian taps with the waveform chain's exact first two moments."""

    def __init__(self, config: Config):
        super().__init__(config)
        self.sums = [TrigSums(self.phases(j)) for j in range(self.frequencies_hz.size)]

    def quadrature_moments(
        self, theta: ArrayLike, multipath: bool = True
    ) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """Mean (n, F, 2) [V^2] and covariance (n, F, 2, 2) [V^4] of (P, Q) = (C0, C3), eq 4 and 16-30."""
        theta = np.atleast_2d(np.asarray(theta, dtype=np.float64))
        n, n_freq = theta.shape[0], self.frequencies_hz.size
        mean = np.empty((n, n_freq, 2))
        cov = np.empty((n, n_freq, 2, 2))
        for j, waveform in enumerate(self.photon_waveforms(theta, multipath)):
            mean[:, j], cov[:, j] = self._affine_moments(waveform, self.sums[j])
            if self.chain.round_photons:
                low = np.flatnonzero(waveform.peak < EXACT_ROUNDING_BELOW_PHOTONS)
                if low.size:
                    mean[low, j], cov[low, j] = self._binwise_moments(waveform, low, self.sums[j])
        return mean, cov

    def _scale(self, sums: TrigSums) -> float:
        return self.config.sensor.demodulation_amplitude_v / sums.bins

    def _affine_moments(self, w: PhotonWaveform, s: TrigSums) -> tuple[NDArray, NDArray]:
        """Moments when the per-bin mean and variance are affine in cos(w t), sin(w t): closed form."""
        chain, k = self.chain, self._scale(s)
        g = chain.volts_per_photon
        dc = g * w.constant + chain.offset_v
        mean_p = k * (dc * s.su + g * w.cosine * s.suu + g * w.sine * s.suv)
        mean_q = k * (dc * s.sv + g * w.cosine * s.suv + g * w.sine * s.svv)
        b = chain.variance_per_photon_v2
        var0 = chain.signal_free_variance_v2 + b * w.constant
        var_c, var_s = b * w.cosine, b * w.sine
        cov_pp = k**2 * (var0 * s.suu + var_c * s.suuu + var_s * s.suuv)
        cov_pq = k**2 * (var0 * s.suv + var_c * s.suuv + var_s * s.suvv)
        cov_qq = k**2 * (var0 * s.svv + var_c * s.suvv + var_s * s.svvv)
        return np.stack([mean_p, mean_q], -1), _cov2(cov_pp, cov_pq, cov_qq)

    def _binwise_moments(self, w: PhotonWaveform, rows: NDArray[np.intp], s: TrigSums) -> tuple[NDArray, NDArray]:
        """Moments summed bin by bin, exact with eq 16 rounding. Cost: O(rows x bins)."""
        k = self._scale(s)
        sub = PhotonWaveform(w.constant[rows], w.cosine[rows], w.sine[rows])
        photons = self.chain.bin_photons(np.maximum(sub.at(s.wt), 0.0))
        mu = self.chain.bin_mean_voltage(photons)
        var = self.chain.bin_voltage_variance(photons)
        mean = k * np.stack([mu @ s.u, mu @ s.v], -1)
        cov = _cov2(k**2 * (var @ (s.u * s.u)), k**2 * (var @ (s.u * s.v)), k**2 * (var @ (s.v * s.v)))
        return mean, cov

    def tap_moments(self, theta: ArrayLike, multipath: bool = True) -> tuple[NDArray, NDArray]:
        """Mean (n, F, 4) [V^2] and the rank-2 covariance (n, F, 4, 4) [V^4] of the four taps."""
        mean, cov = self.quadrature_moments(theta, multipath)
        return mean @ TAPS_FROM_PQ.T, TAPS_FROM_PQ @ cov @ TAPS_FROM_PQ.T

    def taps(self, theta: ArrayLike, rng: np.random.Generator, multipath: bool = True) -> NDArray[np.float64]:
        mean, cov = self.quadrature_moments(theta, multipath)
        z = rng.standard_normal(mean.shape)
        l11 = np.sqrt(np.maximum(cov[..., 0, 0], 0.0))
        l21 = np.divide(cov[..., 0, 1], l11, out=np.zeros_like(l11), where=l11 > 0)
        l22 = np.sqrt(np.maximum(cov[..., 1, 1] - l21**2, 0.0))
        p = mean[..., 0] + l11 * z[..., 0]
        q = mean[..., 1] + l21 * z[..., 0] + l22 * z[..., 1]
        return demod.taps_from_quadratures(p, q)


def _cov2(pp: NDArray, pq: NDArray, qq: NDArray) -> NDArray[np.float64]:
    return np.stack([np.stack([pp, pq], -1), np.stack([pq, qq], -1)], -2)
