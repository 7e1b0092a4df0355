"""The sensor's noise model at a measured amplitude, and what it weighs: the unwrapping of wrapped depths.

:func:`quadrature_noise_v2` is the moment model's (:class:`~mpi_lidar.physics.moments.MomentSensor`) noise of a
tap quadrature for single-path light, :func:`depth_noise_m` the depth noise it gives, :func:`noise_floor_v2` the
amplitude of no light; :func:`unwrapped_rows` turns raw rows of wrapped depths into one range per row, each
frequency weighted by its noise (:func:`mpi_lidar.physics.unwrap.unwrap_depths`).
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import numpy as np
from numpy.typing import NDArray

from mpi_lidar.config import SensorConfig
from mpi_lidar.physics.moments import moment_model
from mpi_lidar.physics.sensor import received_voltage_amplitude
from mpi_lidar.physics.unwrap import unwrap_depths
from mpi_lidar.physics.window import window_corrections_m


def noise_floor_v2(sensor: SensorConfig, frequencies_hz: tuple[float, ...]) -> NDArray[np.float64]:
    """Std of each tap quadrature with no light [V^2]: the amplitude of a pixel with no return is of this order."""
    return quadrature_noise_v2(sensor, frequencies_hz, np.zeros((1, len(frequencies_hz))))[0]


def quadrature_noise_v2(sensor: SensorConfig, frequencies_hz: tuple[float, ...], amplitude_v2: NDArray) -> NDArray:
    """Std of a tap quadrature (n, F) [V^2] for single-path light of the measured amplitudes (n, F) [V^2].

    Shot noise grows with the signal, so the depth noise of a pixel is this over its amplitude, times c / 4 pi f.
    The moment model's variance is a + b A in the amplitude A (thermal and amplifier noise, plus shot noise in
    proportion to the light), so it is worked out at two amplitudes once per sensor and evaluated as that line.
    """
    offset, slope = _quadrature_variance_line(sensor, tuple(frequencies_hz))
    return np.sqrt(offset + slope * np.maximum(amplitude_v2, 0.0))


@lru_cache(maxsize=8)
def _quadrature_variance_line(sensor: SensorConfig, frequencies_hz: tuple[float, ...],
                              ) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Offset [V^4] and slope [V^2] per frequency (F,) of the moment model's quadrature variance against the
    amplitude: its variance at no light, and its growth per V^2 (at 1 V^2)."""
    variance = _moment_quadrature_noise(sensor, frequencies_hz, np.array([[0.0], [1.0]]).repeat(
        len(frequencies_hz), axis=1)) ** 2
    return variance[0], variance[1] - variance[0]


def _moment_quadrature_noise(sensor: SensorConfig, frequencies_hz: tuple[float, ...], amplitude_v2: NDArray,
                             ) -> NDArray:
    """:func:`quadrature_noise_v2` from the moment model's full tap covariance."""
    model = moment_model(sensor, tuple(frequencies_hz))
    r = received_voltage_amplitude(np.maximum(amplitude_v2, 0.0), sensor.modulation_contrast,
                                   sensor.demodulation_amplitude_v)
    waveforms = model.waveforms_from_phasors(r, r.astype(np.complex128))
    _, cov = model.waveform_moments(waveforms)
    return np.sqrt(0.5 * (cov[..., 0, 0] + cov[..., 1, 1]))


def depth_noise_m(sensor: SensorConfig, frequencies_hz: tuple[float, ...], amplitude_v2: NDArray) -> NDArray:
    """Std of the measured depth (n, F) [m] of single-path light of the measured amplitudes (n, F) [V^2].

    sigma_f = sigma_q(Gamma_f) / Gamma_f * c / (4 pi f): the quadrature noise (:func:`quadrature_noise_v2`) over
    the amplitude is the phase noise [rad], and c / 4 pi f [m/rad] turns phase into depth. Amplitudes below
    1e-12 V^2 divide as 1e-12.
    """
    metres_per_rad = sensor.speed_of_light_m_per_s / (4 * np.pi * np.asarray(frequencies_hz, dtype=np.float64))
    noise = quadrature_noise_v2(sensor, tuple(frequencies_hz), amplitude_v2)
    return noise / np.maximum(amplitude_v2, 1e-12) * metres_per_rad[None, :]


def unwrapped_rows(raw: NDArray, frequencies_hz: tuple[float, ...], sensor: SensorConfig,
                   ) -> tuple[NDArray[np.float32], NDArray[np.float64]]:
    """Raw rows (n, 2F) whose depths are each frequency's wrapped depth, with the depths unwrapped into one
    range (:func:`mpi_lidar.physics.unwrap.unwrap_depths`, each weighted by the noise model's sd at its
    amplitude, :func:`depth_noise_m`), and the unwrapping's confidence per row (n,) [1].

    A row whose unwrapping fails (a non-finite value) keeps its measured depths, with confidence 0.
    """
    f = len(frequencies_hz)
    sigma = depth_noise_m(sensor, frequencies_hz, np.asarray(raw[:, f:], dtype=np.float64))
    result = unwrap_depths(raw[:, :f], sigma, frequencies_hz, sensor.speed_of_light_m_per_s)
    rows = np.array(raw, dtype=np.float32)
    moved = np.isfinite(result.depth_m) & (result.wrap_counts != 0)  # a count of 0 keeps the bytes as measured
    rows[:, :f][moved] = result.depth_m[moved]
    return rows, result.confidence


# Fusion keeps a pixel's highest-frequency depth where its frequencies disagree beyond this chi-square p-value
# under the noise model: there a common range is not what they measure (multipath that differs between the
# frequencies, a flying pixel), and the inverse-variance mean would mix their biases.
FUSION_P_VALUE = 1e-3


@dataclass(frozen=True)
class Fused:
    """The frequencies of n pixels fused into one depth each (:func:`fused_depths`).

    depth_m : Inverse-variance weighted mean of the frequencies' depths, less their offsets, (n,). [m]
    sigma_m : Its standard deviation under the noise model, (n,). [m]
    top_sigma_m : The highest frequency's depth's standard deviation, (n,). [m]
    consistent : Whether the frequencies agree within noise (chi-square below its 1 - ``FUSION_P_VALUE``
        quantile), (n,): only those pixels are fused.
    birge_ratio : sqrt(chi2 / (F - 1)), the spread of the frequencies over what the noise explains, (n,). [1]
    """

    depth_m: NDArray[np.float32]
    sigma_m: NDArray[np.float32]
    top_sigma_m: NDArray[np.float32]
    consistent: NDArray[np.bool_]
    birge_ratio: NDArray[np.float32]


def fused_depths(raw: NDArray, frequencies_hz: tuple[float, ...], sensor: SensorConfig, *,
                 noise_scale: float = 1.0, offsets_m: NDArray | tuple[float, ...] | None = None,
                 window: bool = False) -> Fused:
    """Maximum-likelihood depth of raw rows (n, 2F) of unwrapped depths [m] and amplitudes [V^2]: each frequency's
    depth less its offset, weighted by the inverse variance of the noise model at its amplitude.

    Under independent Gaussian noise of sds sigma_f the mean sum_f w_f d_f / sum_f w_f with w_f = sigma_f^-2 is the
    maximum-likelihood range and reaches the Cramer-Rao bound, sigma = (sum_f w_f)^-1/2: at 12.5-31.25 MHz about
    0.68 of the highest frequency's sd. ``offsets_m`` (F,): each frequency's fixed depth offset relative to the
    highest (a sensor's, as ``mpi-lidar calibrate`` measures it), subtracted first; None: none. ``noise_scale``
    scales every sd (a sensor's noise over the model's): it moves the sds and the consistency test, not the mean.
    ``window``: each depth first has the integration window's leakage removed
    (:func:`~mpi_lidar.physics.window.window_corrections_m`), the offsets then being those that remain.
    """
    f = len(frequencies_hz)
    window_m = window_corrections_m(raw[:, :f], raw[:, f:], tuple(frequencies_hz), sensor) if window else None
    offsets = np.zeros(f) if offsets_m is None else np.asarray(offsets_m, dtype=np.float64)
    # The variance is a + b A per frequency (quadrature_noise_v2): one line per column, summed column by column,
    # since a row reduction over F values is several times slower.
    line_offset, line_slope = _quadrature_variance_line(sensor, tuple(frequencies_hz))
    metres_per_rad = sensor.speed_of_light_m_per_s / (4 * np.pi * np.asarray(frequencies_hz, dtype=np.float64))
    scale2 = noise_scale**2
    depths, weights = [], []
    for column in range(f):
        amplitude = np.maximum(raw[:, f + column].astype(np.float64), 1e-12)
        variance = scale2 * (line_offset[column] + line_slope[column] * amplitude) / amplitude**2
        weights.append(1.0 / (variance * metres_per_rad[column] ** 2))
        depth = raw[:, column].astype(np.float64) - offsets[column]
        depths.append(depth if window_m is None else depth + window_m[:, column])
    total = sum(weights[1:], weights[0])
    mean = sum((w * d for w, d in zip(weights[1:], depths[1:], strict=True)), weights[0] * depths[0]) / total
    chi2 = sum(w * (d - mean) ** 2 for w, d in zip(weights, depths, strict=True))
    top = int(np.argmax(frequencies_hz))
    with np.errstate(invalid="ignore"):  # rows without a finite depth: NaN chi2, not consistent
        consistent = chi2 <= _chi2_quantile(f - 1)
    return Fused(mean.astype(np.float32), (total**-0.5).astype(np.float32),
                 (weights[top] ** -0.5).astype(np.float32), consistent,
                 np.sqrt(chi2 / max(f - 1, 1)).astype(np.float32))


@lru_cache(maxsize=8)
def _chi2_quantile(dof: int) -> float:
    """The 1 - ``FUSION_P_VALUE`` quantile of chi-square with ``dof`` degrees of freedom (inf for none)."""
    if dof < 1:
        return float("inf")
    from scipy.special import chdtri  # scipy.stats costs a second of imports; the special function does not

    return float(chdtri(dof, FUSION_P_VALUE))
