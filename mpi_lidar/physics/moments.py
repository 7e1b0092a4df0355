"""Moment-matched simulator: the exact mean and covariance of the taps, sampled as a Gaussian.

Each tap is a weighted sum of ~2667 independent bin voltages (eq 4), so it is Gaussian to high accuracy.
Its mean and covariance follow exactly from the per-bin means and variances of the detector chain
(eq 16-30). Since the expected photon count per bin is X0 + Xc cos(w t) + Xs sin(w t) and the per-bin
variance is affine in it, every sum over bins reduces to a handful of trigonometric sums fixed per
frequency, and the cost no longer grows with the number of bins. The only non-affine step, rounding the
photon count (eq 16), is summed bin by bin, exactly. Rounding errors do not average out over the window:
the bin phases repeat every P bins (P = 40, 80, 20, 16 at 12.5, 18.75, 25, 31.25 MHz with 6 ns bins), so
the error pattern repeats too and adds up coherently (about 0.5 / peak photons rad). The sum over the
window is therefore folded onto one period with integer weights: exact, at a cost of P bins, not 2667.

In parallel-phase demodulation C2 = -C0 and C3 = -C1, so the taps live in two dimensions: the in-phase
sum P = C0 and the quadrature sum Q = C3; their 4x4 covariance has rank 2.
"""

from __future__ import annotations

from functools import lru_cache

import numpy as np
from numpy.typing import ArrayLike, NDArray

from mpi_lidar.config import Config, SensorConfig, SimulatorConfig
from mpi_lidar.physics import demod
from mpi_lidar.physics.sensor import PhotonWaveform, SensorModel

# Maps (P, Q) to the four taps (C0, C1, C2, C3) = (P, -Q, -P, Q).
TAPS_FROM_PQ = np.array([[1.0, 0.0], [0.0, -1.0], [-1.0, 0.0], [0.0, 1.0]])


class TrigSums:
    """Sums over the integration window of products of u = cos(w t_i) and v = sin(w t_i)."""

    def __init__(self, wt: NDArray[np.float64], period: int):
        u, v = np.cos(wt), np.sin(wt)
        self.bins = wt.size
        # Bin i and bin i + period share their phase: fold the window onto one period with integer weights.
        weight = self.bins // period + (np.arange(period) < self.bins % period)
        self.fold_u, self.fold_v = u[:period], v[:period]
        fu, fv = self.fold_u, self.fold_v
        # Columns: the weighted u, v, uu, uv, vv of each bin of the period, and their totals.
        self.fold_basis = weight[:, None] * np.stack([fu, fv, fu * fu, fu * fv, fv * fv], axis=1)
        self.fold_totals = self.fold_basis.sum(0)
        self.su, self.sv = u.sum(), v.sum()
        self.suu, self.suv, self.svv = (u * u).sum(), (u * v).sum(), (v * v).sum()
        self.suuu, self.suuv = (u**3).sum(), (u * u * v).sum()
        self.suvv, self.svvv = (u * v * v).sum(), (v**3).sum()


class MomentSensor(SensorModel):
    """Default simulator: Gaussian taps with the waveform chain's exact first two moments."""

    def __init__(self, config: Config):
        super().__init__(config)
        self.sums = [TrigSums(self.phases(j), self._period(j)) for j in range(self.frequencies_hz.size)]

    def _period(self, j: int) -> int:
        """Bins after which the bin phases repeat, or the whole window if they do not repeat within it."""
        try:
            return demod.whole_cycle_bins(self.frequencies_hz[j], self.config.sensor.transit_time_s, self.bins[j])
        except ValueError:
            return self.bins[j]

    def quadrature_moments(
        self, theta: ArrayLike, multipath: bool = True
    ) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """Mean (n, F, 2) [V^2] and covariance (n, F, 2, 2) [V^4] of (P, Q) = (C0, C3), eq 4 and 16-30."""
        return self.waveform_moments(self.photon_waveforms(theta, multipath))

    def waveform_moments(self, waveforms: list[PhotonWaveform]) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """Mean and covariance of (P, Q) for given photon waveforms, one per frequency."""
        n, n_freq = waveforms[0].constant.size, self.frequencies_hz.size
        mean = np.empty((n, n_freq, 2))
        cov = np.empty((n, n_freq, 2, 2))
        for j, waveform in enumerate(waveforms):
            moments = self._binwise_moments if self.chain.round_photons else self._affine_moments
            mean[:, j], cov[:, j] = moments(waveform, self.sums[j])
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

    def _binwise_moments(self, w: PhotonWaveform, s: TrigSums) -> tuple[NDArray, NDArray]:
        """Moments summed bin by bin over one folded period, exact with eq 16 rounding."""
        chain, k = self.chain, self._scale(s)
        expected = w.constant[:, None] + w.cosine[:, None] * s.fold_u + w.sine[:, None] * s.fold_v
        photon_sums = chain.bin_photons(np.maximum(expected, 0.0)) @ s.fold_basis  # (n, 5)
        # Per-bin mean g n + offset and variance a + b n are affine in the rounded count n.
        mean = k * (chain.volts_per_photon * photon_sums[:, :2] + chain.offset_v * s.fold_totals[:2])
        var = k**2 * (chain.variance_per_photon_v2 * photon_sums[:, 2:]
                      + chain.signal_free_variance_v2 * s.fold_totals[2:])
        return mean, _cov2(var[:, 0], var[:, 1], var[:, 2])

    def tap_moments(self, theta: ArrayLike, multipath: bool = True) -> tuple[NDArray, NDArray]:
        """Mean (n, F, 4) [V^2] and the rank-2 covariance (n, F, 4, 4) [V^4] of the four taps."""
        mean, cov = self.quadrature_moments(theta, multipath)
        return mean @ TAPS_FROM_PQ.T, TAPS_FROM_PQ @ cov @ TAPS_FROM_PQ.T

    def sample_taps(self, waveforms: list[PhotonWaveform], rng: np.random.Generator) -> NDArray[np.float64]:
        mean, cov = self.waveform_moments(waveforms)
        z = rng.standard_normal(mean.shape)
        l11 = np.sqrt(np.maximum(cov[..., 0, 0], 0.0))
        l21 = np.divide(cov[..., 0, 1], l11, out=np.zeros_like(l11), where=l11 > 0)
        l22 = np.sqrt(np.maximum(cov[..., 1, 1] - l21**2, 0.0))
        p = mean[..., 0] + l11 * z[..., 0]
        q = mean[..., 1] + l21 * z[..., 0] + l22 * z[..., 1]
        return demod.taps_from_quadratures(p, q)


@lru_cache(maxsize=4)
def moment_model(sensor: SensorConfig, frequencies_hz: tuple[float, ...]) -> MomentSensor:
    """The moment model of ``sensor`` at ``frequencies_hz`` with the default window, rounding off: the closed-form
    moments, which is all a noise prediction or the window's leakage (:mod:`mpi_lidar.physics.window`) needs."""
    return MomentSensor(Config(sensor=sensor, frequencies_hz=frequencies_hz,
                               simulator=SimulatorConfig(round_photons=False)))


def _cov2(pp: NDArray, pq: NDArray, qq: NDArray) -> NDArray[np.float64]:
    return np.stack([np.stack([pp, pq], -1), np.stack([pq, qq], -1)], -2)
