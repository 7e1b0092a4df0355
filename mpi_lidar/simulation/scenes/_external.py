"""Scans from external renders: correlation phasors or transient histograms through the sensor model."""

from __future__ import annotations

from typing import TYPE_CHECKING, Unpack

import numpy as np
from numpy.typing import NDArray

from mpi_lidar.config import Config
from mpi_lidar.scans.scan import Scan
from mpi_lidar.simulation.scenes._render import sense

if TYPE_CHECKING:
    from mpi_lidar.scans.scan import ScanExtras


def scan_from_phasors(name: str, gamma_phasor: NDArray, config: Config, rng: np.random.Generator,
                      dc_gamma: NDArray | None = None, **optional: Unpack[ScanExtras]) -> Scan:
    """A scan from externally rendered correlation phasors (F, H, W) [V^2] (eq 11) through our sensor model.

    ``dc_gamma`` (F, H, W) is the sum of the path magnitudes [V^2]; without it the magnitude of the phasor
    is used, which is exact for one path per pixel and a lower bound otherwise.
    """
    phasor = np.asarray(gamma_phasor, dtype=np.complex128)
    f, h, w = phasor.shape
    dc = np.abs(phasor) if dc_gamma is None else np.asarray(dc_gamma, dtype=np.float64)
    depth, amplitude = sense(phasor.reshape(f, -1).T, dc.reshape(f, -1).T, config, rng)
    return Scan(name=name, frequencies_hz=config.frequencies_hz, depth=depth.reshape(f, h, w).astype(np.float32),
                amplitude=amplitude.reshape(f, h, w).astype(np.float32),
                speed_of_light_m_per_s=config.sensor.speed_of_light_m_per_s, **optional)


def scan_from_transient(name: str, histogram: NDArray, bin_s: float, config: Config, rng: np.random.Generator,
                        **optional: Unpack[ScanExtras]) -> Scan:
    """A scan from transient histograms (T, H, W): correlation amplitude [V^2] per round-trip-time bin [s].

    The phasor at f is sum_t h(t) e^{j 2 pi f t} (t the bin's round-trip time) and the DC part sum_t h(t).
    """
    h = np.asarray(histogram, dtype=np.float64)
    times = np.arange(h.shape[0]) * bin_s
    # e^{+j 2 pi f t} with t = 2 d / c: the phasor convention of mpi_lidar.physics.transport
    kernel = np.exp(2j * np.pi * np.outer(config.frequencies_hz, times))  # (F, T)
    phasor = np.tensordot(kernel, h, axes=(1, 0))  # (F, H, W)
    dc = np.broadcast_to(h.sum(0), phasor.shape)
    return scan_from_phasors(name, phasor, config, rng, dc_gamma=dc, **optional)
