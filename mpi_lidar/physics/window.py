"""The integration window's leakage: the fixed depth error of taps summed over a window of a fraction of a cycle
more than whole modulation cycles, and its removal.

Over K bins that do not span whole cycles, the window's cosines u = cos(w t_i) and sines v = sin(w t_i) are
neither orthogonal nor of zero sum, so the mean quadratures of light with the phasor X = (Xc, Xs) [photons per
bin] and the constant part X0 are (P, Q) = k (dc s + g M X) (:class:`~mpi_lidar.physics.moments.MomentSensor`),
with k = m / K, g the volts per photon, dc = g X0 + the chain's signal-free offset [V], s = (sum u, sum v) and
M = [[sum uu, sum uv], [sum uv, sum vv]]. The measured phase atan2(Q, P) is then off: at the default 16 us
window of 6 ns bins by up to 0.6 mm of depth at 12.5 MHz and 0.3 mm at 31.25 MHz, a function of the phase and,
through dc, of the amplitude. A sensor sees it as each frequency's range offset, slowly varying with range.

For single-path light X0 = |X| / alpha (the modulation contrast), so the map from X to (P, Q) is known and is
inverted here: the phasor, and its phase, come back exactly from the measured ones. What remains is the error of
rounding each bin's photon count (about 0.5 / peak photons rad, the moment model's note), which no closed form
inverts; it matters only at a few photons per bin, where the noise is far larger.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import numpy as np
from numpy.typing import NDArray

from mpi_lidar.config import SensorConfig
from mpi_lidar.physics.moments import moment_model


@dataclass(frozen=True)
class _Leakage:
    """One frequency's window as a phase error: the true phase less the measured one phi is, to first order in the
    leakage (1e-3, so to about 1e-6 rad), constant + c2 cos 2 phi + s2 sin 2 phi + (s1 + s1_per_v2 / A) sin phi
    + (c1 + c1_per_v2 / A) cos phi [rad] at the amplitude A [V^2]."""

    constant: float
    c2: float
    s2: float
    s1: float
    c1: float
    s1_per_v2: float
    c1_per_v2: float
    metres_per_rad: float

    def phase_correction(self, phase: NDArray, amplitude_v2: NDArray) -> NDArray:
        cos, sin = np.cos(phase), np.sin(phase)
        first_cos: float | NDArray = self.c1
        first_sin: float | NDArray = self.s1
        if self.c1_per_v2 or self.s1_per_v2:  # a chain without signal-free offset has none: its 1 / A is skipped
            inverse = 1.0 / amplitude_v2
            first_cos, first_sin = self.c1 + self.c1_per_v2 * inverse, self.s1 + self.s1_per_v2 * inverse
        # c2 cos 2 phi + s2 sin 2 phi + s1 sin phi + c1 cos phi, factored to fewer passes over the pixels
        return self.constant + cos * (self.c2 * cos + 2 * self.s2 * sin + first_cos) + sin * (first_sin - self.c2 * sin)


def window_corrections_m(depth_m: NDArray, amplitude_v2: NDArray, frequencies_hz: tuple[float, ...],
                         sensor: SensorConfig) -> NDArray[np.float32]:
    """What to add to each frequency's measured depth (n, F) [m] so that it is the range an ideal window would
    have measured, from the depths (n, F) [m] and amplitudes (n, F) [V^2] of single-path light. 0 where the
    window spans whole cycles; NaN where a depth or an amplitude is not finite."""
    # float32 is plenty: the corrections are 1e-4 of a radian, their relative error that of the phase (1e-7).
    depth = np.asarray(depth_m, dtype=np.float32)
    amplitude = np.asarray(amplitude_v2, dtype=np.float32)
    corrections = np.empty(np.broadcast_shapes(depth.shape, amplitude.shape), dtype=np.float32)
    for column, leakage in enumerate(_leakages(sensor, tuple(frequencies_hz))):
        phase = depth[:, column] * np.float32(1.0 / leakage.metres_per_rad)
        corrections[:, column] = leakage.phase_correction(phase, amplitude[:, column]) * leakage.metres_per_rad
    return corrections


@lru_cache(maxsize=8)
def _leakages(sensor: SensorConfig, frequencies_hz: tuple[float, ...]) -> tuple[_Leakage, ...]:
    """Each frequency's :class:`_Leakage`.

    In the units of an ideal window (k g K / 2 per photon, so that the phasor X' is what it measures [V^2]) the
    quadratures are Z = (I + E)^-1 X' + l |X'| + o, with I + E = (M / (K / 2))^-1, the constant part X0 = |X| / alpha
    leaking l = s / (K / 2) / alpha per unit of phasor size and the chain's offset o = k offset_v s. With
    Z = A (cos phi, sin phi), X' = (I + E) (Z - l A - o), and the true phase less phi is (X'_s cos - X'_c sin) / A
    to first order in E, l and o / A: the terms of :class:`_Leakage`.
    """
    model = moment_model(sensor, frequencies_hz)
    leakages = []
    for sums, frequency in zip(model.sums, frequencies_hz, strict=True):
        half = sums.bins / 2
        s = np.array([sums.su, sums.sv]) / half
        e = np.linalg.inv(np.array([[sums.suu, sums.suv], [sums.suv, sums.svv]]) / half) - np.eye(2)
        leak = s / sensor.modulation_contrast
        offset = s * half * (sensor.demodulation_amplitude_v / sums.bins) * model.chain.offset_v
        leakages.append(_Leakage(
            constant=float(e[1, 0] - e[0, 1]) / 2, c2=float(e[1, 0] + e[0, 1]) / 2, s2=float(e[1, 1] - e[0, 0]) / 2,
            s1=float(leak[0]), c1=-float(leak[1]), s1_per_v2=float(offset[0]), c1_per_v2=-float(offset[1]),
            metres_per_rad=sensor.speed_of_light_m_per_s / (4 * np.pi * frequency)))
    return tuple(leakages)
