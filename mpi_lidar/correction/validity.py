"""Which pixels can be trusted at all: finite, above the noise floor, unsaturated, frequencies consistent."""

from __future__ import annotations

from functools import lru_cache

import numpy as np
from numpy.typing import NDArray

from mpi_lidar.config import Config, SensorConfig, SimulatorConfig
from mpi_lidar.correction.options import INVALID_FLAGS, CorrectionOptions, Flag
from mpi_lidar.physics.moments import MomentSensor
from mpi_lidar.physics.sensor import received_voltage_amplitude


@lru_cache(maxsize=4)
def _noise_model(sensor: SensorConfig, frequencies_hz: tuple[float, ...]) -> MomentSensor:
    # Rounding off: the closed-form moments, which is all a noise prediction needs.
    return MomentSensor(Config(sensor=sensor, frequencies_hz=frequencies_hz,
                               simulator=SimulatorConfig(round_photons=False)))


def noise_floor_v2(sensor: SensorConfig, frequencies_hz: tuple[float, ...]) -> NDArray[np.float64]:
    """Std of each tap quadrature with no light [V^2]: the amplitude of a pixel with no return is of this order."""
    return quadrature_noise_v2(sensor, frequencies_hz, np.zeros((1, len(frequencies_hz))))[0]


def quadrature_noise_v2(sensor: SensorConfig, frequencies_hz: tuple[float, ...], amplitude_v2: NDArray) -> NDArray:
    """Std of a tap quadrature (n, F) [V^2] for single-path light of the measured amplitudes (n, F) [V^2].

    Shot noise grows with the signal, so the depth noise of a pixel is this over its amplitude, times c / 4 pi f.
    """
    model = _noise_model(sensor, tuple(frequencies_hz))
    r = received_voltage_amplitude(np.maximum(amplitude_v2, 0.0), sensor.modulation_contrast,
                                   sensor.demodulation_amplitude_v)
    waveforms = model.waveforms_from_phasors(r, r.astype(np.complex128))
    _, cov = model.waveform_moments(waveforms)
    return np.sqrt(0.5 * (cov[..., 0, 0] + cov[..., 1, 1]))


def validity_flags(raw: NDArray, frequencies_hz: tuple[float, ...], options: CorrectionOptions,
                   sensor: SensorConfig) -> NDArray[np.uint8]:
    """Flag per pixel: NOT_NEEDED for valid pixels (the gate decides later), else the first reason it is invalid."""
    f = len(frequencies_hz)
    depth, amplitude = raw[:, :f], raw[:, f:]
    flags = np.full(raw.shape[0], Flag.NOT_NEEDED, dtype=np.uint8)
    high = low = depth[:, 0]
    for column in range(1, f):  # column by column: a row reduction over F values is several times slower
        high, low = np.maximum(high, depth[:, column]), np.minimum(low, depth[:, column])
    spread = high - low  # NaN where a depth is NaN, as a row's max - min: those rows are NOT_FINITE
    floor = options.min_amplitude_sigmas * noise_floor_v2(sensor, tuple(frequencies_hz))
    rules = [
        (Flag.INCONSISTENT, spread > options.max_depth_spread_m),
        (Flag.SATURATED, (amplitude > options.saturation_amplitude_v2).any(axis=1)),
        (Flag.NO_RETURN, (amplitude < floor[None, :]).any(axis=1)),
        (Flag.NOT_FINITE, ~np.isfinite(raw).all(axis=1)),
    ]
    for flag, where in rules:  # later rules win: the most basic reason is reported
        flags[where] = flag
    return flags



def depth_noise_m(sensor: SensorConfig, frequencies_hz: tuple[float, ...], amplitude_v2: NDArray) -> NDArray:
    """Std of the measured depth (n, F) [m] of single-path light of the measured amplitudes (n, F) [V^2].

    sigma_f = sigma_q(Gamma_f) / Gamma_f * c / (4 pi f): the quadrature noise (:func:`quadrature_noise_v2`) over
    the amplitude is the phase noise [rad], and c / 4 pi f [m/rad] turns phase into depth. Amplitudes below
    1e-12 V^2 divide as 1e-12.
    """
    metres_per_rad = sensor.speed_of_light_m_per_s / (4 * np.pi * np.asarray(frequencies_hz, dtype=np.float64))
    noise = quadrature_noise_v2(sensor, tuple(frequencies_hz), amplitude_v2)
    return noise / np.maximum(amplitude_v2, 1e-12) * metres_per_rad[None, :]


def usable_depth_of(raw: NDArray, flags: NDArray) -> NDArray:
    """The highest-frequency depth (n,) [m] of raw rows (n, 2F) whose ``flags`` (n,) are not invalid
    (:data:`INVALID_FLAGS`), NaN elsewhere: what the scene geometry is worked out from."""
    f = raw.shape[1] // 2
    return np.where(~np.isin(flags, [int(flag) for flag in INVALID_FLAGS]), raw[:, f - 1], np.nan)
