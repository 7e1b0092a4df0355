"""Discrete-time facts of the integration window, shared by the configuration's validation and the demodulation.

The sensor sums its taps over bins of one carrier transit time; whether a modulation frequency completes a
whole number of cycles within some number of bins is pure arithmetic on (frequency, bin width), needed both
where a configuration is checked (:mod:`mpi_lidar.config`) and where the window is chosen
(:mod:`mpi_lidar.physics.demod`). It lives here, below both, so that the configuration imports nothing of
the physics.
"""

from __future__ import annotations


def whole_cycle_bins(frequency_hz: float, bin_s: float, max_bins: int = 1_000_000) -> int:
    """Fewest bins that span a whole number of cycles (exactly, or to 1e-9 cycles).

    Parameters
    ----------
    frequency_hz : Modulation frequency. [Hz]
    bin_s : Width of one bin (the carrier transit time). [s]
    max_bins : Largest bin count tried.

    Raises
    ------
    ValueError : no count up to ``max_bins`` spans whole cycles.
    """
    cycles_per_bin = frequency_hz * bin_s
    for bins in range(1, max_bins + 1):
        cycles = cycles_per_bin * bins
        if abs(cycles - round(cycles)) < 1e-9 and round(cycles) >= 1:
            return bins
    raise ValueError(f"{frequency_hz:g} Hz has no whole-cycle window of bins of {bin_s:g} s")
