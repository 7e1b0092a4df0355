"""Parallel-phase 4-tap demodulation (paper eq 2-7), usable on simulated or real raw taps.

Tap n correlates the detector voltage with m*cos(w t + n*pi/2). Because C2 = -C0 and C3 = -C1 for an
ideal sinusoid, the taps carry two numbers per frequency: the in-phase and quadrature sums.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

from mpi_lidar.timing import whole_cycle_bins  # lives below config; also reached as demod.whole_cycle_bins

TAP_SHIFTS_RAD = np.array([0.0, 0.5, 1.0, 1.5]) * np.pi


def integration_bins(integration_time_s: float, bin_s: float, frequency_hz: float, whole_cycles: bool) -> int:
    """Number of bins K the taps sum over.

    ``round(T_int / bin)`` (2667 for 16 us / 6 ns), which is not a whole number of modulation cycles and
    leaves a small fixed depth error. With ``whole_cycles`` K is the nearest multiple of the shortest bin
    count that spans whole cycles, so the sinusoids are orthogonal over the window and the error vanishes.

    Parameters
    ----------
    integration_time_s : Integration time. [s]
    bin_s : Width of one bin (the carrier transit time). [s]
    frequency_hz : Modulation frequency. [Hz]
    whole_cycles : Snap K to whole modulation cycles.
    """
    k = round(integration_time_s / bin_s)
    if not whole_cycles:
        return k
    period = whole_cycle_bins(frequency_hz, bin_s)
    return max(period, round(k / period) * period)


def bin_times(bins: int, bin_s: float) -> NDArray[np.float64]:
    """Bin start times t_i = i * bin. [s]"""
    return np.arange(bins, dtype=np.float64) * bin_s


def correlate_taps(
    voltage: NDArray[np.float64], frequency_hz: float, bin_s: float, demod_amplitude_v: float
) -> NDArray[np.float64]:
    """The four taps C_n = (m/K) sum_i V_i cos(w t_i + n pi/2), eq 4 in discrete time, in float64.

    Parameters
    ----------
    voltage : Detector voltage per bin, shape (..., K). [V]
    frequency_hz : Modulation frequency. [Hz]
    bin_s : Width of one bin. [s]
    demod_amplitude_v : Amplitude m of the demodulation signal, eq 2. [V]

    Returns
    -------
    Taps, shape (..., 4). [V^2]
    """
    bins = voltage.shape[-1]
    wt = 2 * np.pi * frequency_hz * bin_times(bins, bin_s)
    reference = np.cos(wt[:, None] + TAP_SHIFTS_RAD[None, :])  # (K, 4)
    return (demod_amplitude_v / bins) * (np.asarray(voltage, dtype=np.float64) @ reference)


def taps_from_quadratures(in_phase: ArrayLike, quadrature: ArrayLike) -> NDArray[np.float64]:
    """Taps (P, -Q, -P, Q) from P = C0 and Q = C3 of an ideal parallel-phase demodulator. [V^2]"""
    p = np.asarray(in_phase, dtype=np.float64)
    q = np.asarray(quadrature, dtype=np.float64)
    return np.stack([p, -q, -p, q], axis=-1)


def phase_from_taps(taps: ArrayLike) -> NDArray[np.float64]:
    """Phase delay, eq 5, taken with atan2 and wrapped to [0, 2 pi) so no depth jumps by a whole range.

    Differences are formed in float64: taps carry a large DC part, and float32 differencing loses mm.

    Parameters
    ----------
    taps : Taps (C0, C1, C2, C3) along the last axis. [V^2]
    """
    c = np.asarray(taps, dtype=np.float64)
    phase = np.mod(np.arctan2(c[..., 3] - c[..., 1], c[..., 0] - c[..., 2]), 2 * np.pi)
    # np.mod(-tiny, 2 pi) rounds to exactly 2 pi; that phase is 0.
    return np.where(phase >= 2 * np.pi, 0.0, phase)


def amplitude_from_taps(taps: ArrayLike) -> NDArray[np.float64]:
    """Amplitude of the cross correlation, eq 6. [V^2]"""
    c = np.asarray(taps, dtype=np.float64)
    return np.hypot(c[..., 3] - c[..., 1], c[..., 2] - c[..., 0]) / 2


def depth_from_phase(phase: ArrayLike, frequency_hz: ArrayLike, c: float) -> NDArray[np.float64]:
    """Depth from phase, eq 7: d = c phi / (4 pi f).

    Parameters
    ----------
    phase : Phase delay. [rad]
    frequency_hz : Modulation frequency, broadcast against phase. [Hz]
    c : Speed of light. [m/s]
    """
    # c * phi first, as the datasets were made: the same bits
    return c * np.asarray(phase, dtype=np.float64) / (4 * np.pi * np.asarray(frequency_hz, dtype=np.float64))


def depth_and_amplitude(
    taps: ArrayLike, frequencies_hz: ArrayLike, c: float
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Depth [m] and amplitude [V^2] from taps of shape (..., F, 4), eq 5-7."""
    freqs = np.asarray(frequencies_hz, dtype=np.float64)
    return depth_from_phase(phase_from_taps(taps), freqs, c), amplitude_from_taps(taps)


def metres_per_radian(frequency_hz: ArrayLike, c: float) -> NDArray[np.float64]:
    """Depth per radian of phase at a modulation frequency, c / (4 pi f) (eq 7). [m/rad]

    Parameters
    ----------
    frequency_hz : Modulation frequency. [Hz]
    c : Speed of light the phase is converted with. [m/s]
    """
    return c / (4 * np.pi * np.asarray(frequency_hz, dtype=np.float64))


def unambiguous_range(frequency_hz: ArrayLike, c: float) -> NDArray[np.float64]:
    """Depth at which the phase wraps, c / (2 f). [m]"""
    return c / (2 * np.asarray(frequency_hz, dtype=np.float64))
