"""The sensor's noise at a measured amplitude, and everything it weighs: unwrapping, consistency and fusion.

:class:`NoiseModel` is the one object every stage of a scan's correction asks: each frequency's quadrature
variance is a line in the amplitude, sigma_q^2 = a_f + b_f A (read and thermal noise, plus shot noise in proportion
to the light), times a noise scale; the depth noise is sigma_q / A times c / 4 pi f. The default sensor's lines come
from the moment model (:class:`~mpi_lidar.physics.moments.MomentSensor`, :meth:`NoiseModel.for_sensor`); a law
measured from a scan is the same object with other coefficients. The module's functions (:func:`depth_noise_m`,
:func:`noise_floor_v2`, :func:`unwrapped_rows`, :func:`fused_depths`) are the default sensor's model, for the
simulator and the benchmarks.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from functools import lru_cache

import numpy as np
from numpy.typing import NDArray

from mpi_lidar.config import SensorConfig
from mpi_lidar.physics.demod import metres_per_radian
from mpi_lidar.physics.moments import moment_model
from mpi_lidar.physics.sensor import received_voltage_amplitude
from mpi_lidar.physics.unwrap import unwrap_depths
from mpi_lidar.physics.window import window_corrections_m

# Amplitudes below this [V^2] divide as this: a pixel without light has an unbounded, not an infinite, noise.
MIN_AMPLITUDE_V2 = 1e-12
# A frequency whose amplitude lies below this many times its no-light noise is taken to have no light: its phase is
# then uniform over the circle, not the Gaussian its amplitude's weight assumes, and fusion leaves it out of that
# pixel. With no light the amplitude passes it in exp(-3^2 / 2) = 1.1 % of pixels; a frequency with light at 3 sds
# carries under a ninth of the weight of one at 10.
NO_LIGHT_SIGMAS = 3.0
LIT_SHARE = 0.5


@dataclass(frozen=True, eq=False)
class NoiseModel:
    """One scan's depth noise per frequency, built once and handed to every stage that weighs a measurement.

    The quadrature variance of frequency f at amplitude A [V^2] is ``noise_scale^2 (a_f + b_f A)``; the depth sd is
    its root over A times c / (4 pi f) (eq 7).

    Attributes
    ----------
    frequencies_hz : Modulation frequencies (F,). [Hz]
    speed_of_light_m_per_s : The speed of light phases are converted with. [m/s]
    read_variance_v4 : a_f, the quadrature variance with no light (F,). [V^4]
    shot_variance_v2 : b_f, its growth per unit of amplitude (F,). [V^2]
    noise_scale : The sensor's noise over these lines (a sensor profile's ``noise_scale``). [1]
    sensor : The sensor whose integration window's leakage fusion may remove
        (:func:`~mpi_lidar.physics.window.window_corrections_m`).
    """

    frequencies_hz: tuple[float, ...]
    speed_of_light_m_per_s: float
    read_variance_v4: NDArray[np.float64]
    shot_variance_v2: NDArray[np.float64]
    noise_scale: float
    sensor: SensorConfig

    @classmethod
    def for_sensor(cls, sensor: SensorConfig, frequencies_hz: tuple[float, ...], noise_scale: float = 1.0,
                   ) -> NoiseModel:
        """The moment model's noise of ``sensor`` (Table I's law by default), scaled by ``noise_scale``."""
        offset, slope = _quadrature_variance_line(sensor, tuple(frequencies_hz))
        return cls(tuple(frequencies_hz), sensor.speed_of_light_m_per_s, offset, slope, float(noise_scale), sensor)

    def scaled(self, noise_scale: float) -> NoiseModel:
        """The same law with another noise scale."""
        return replace(self, noise_scale=float(noise_scale))

    @property
    def metres_per_radian(self) -> NDArray[np.float64]:
        """c / (4 pi f) per frequency (F,). [m/rad]"""
        return metres_per_radian(self.frequencies_hz, self.speed_of_light_m_per_s)

    def quadrature_sigma_v2(self, amplitude_v2: NDArray) -> NDArray:
        """Std of a tap quadrature (n, F) [V^2] for single-path light of the measured amplitudes (n, F) [V^2]."""
        sigma = np.sqrt(self.read_variance_v4 + self.shot_variance_v2 * np.maximum(amplitude_v2, 0.0))
        return sigma if self.noise_scale == 1.0 else self.noise_scale * sigma

    @property
    def floor_v2(self) -> NDArray[np.float64]:
        """Std of each tap quadrature with no light (F,) [V^2]: the amplitude of a pixel with no return."""
        return self.quadrature_sigma_v2(np.zeros((1, len(self.frequencies_hz))))[0]

    def depth_sigma_m(self, amplitude_v2: NDArray) -> NDArray:
        """Std of the measured depth (n, F) [m] of single-path light of the measured amplitudes (n, F) [V^2].

        sigma_f = sigma_q(A_f) / A_f * c / (4 pi f): the quadrature noise over the amplitude is the phase noise
        [rad]. Amplitudes below ``MIN_AMPLITUDE_V2`` divide as it.
        """
        noise = self.quadrature_sigma_v2(amplitude_v2)
        return noise / np.maximum(amplitude_v2, MIN_AMPLITUDE_V2) * self.metres_per_radian[None, :]

    def unwrap(self, raw: NDArray, *, equal_amplitudes: bool = False,
               ) -> tuple[NDArray[np.float32], NDArray[np.float64]]:
        """Raw rows (n, 2F) of wrapped depths [m] and amplitudes [V^2] with the depths unwrapped into one range, and
        the unwrapping's confidence per row (n,) [1] (:func:`mpi_lidar.physics.unwrap.unwrap_depths`).

        Each frequency is weighted by its depth sd at its amplitude; ``equal_amplitudes``: by the sd's shape at one
        amplitude, 1 / f, for amplitudes whose unit is not known yet. A row whose unwrapping fails (a non-finite
        value) keeps its measured depths, with confidence 0; a row that takes no wrap count keeps its bytes.
        """
        f = len(self.frequencies_hz)
        if equal_amplitudes:
            sigma = np.broadcast_to(1.0 / np.asarray(self.frequencies_hz), (raw.shape[0], f))
        else:
            sigma = self.depth_sigma_m(np.asarray(raw[:, f:], dtype=np.float64))
        result = unwrap_depths(raw[:, :f], sigma, self.frequencies_hz, self.speed_of_light_m_per_s)
        rows = np.array(raw, dtype=np.float32)
        moved = np.isfinite(result.depth_m) & (result.wrap_counts != 0)  # a count of 0 keeps the bytes as measured
        rows[:, :f][moved] = result.depth_m[moved]
        return rows, result.confidence

    def fuse(self, raw: NDArray, *, offsets_m: NDArray | tuple[float, ...] | None = None,
             window: bool = False) -> Fused:
        """Maximum-likelihood depth of raw rows (n, 2F) of unwrapped depths [m] and amplitudes [V^2]: each
        frequency's depth less its offset, weighted by its inverse variance at its amplitude.

        Under independent Gaussian noise of sds sigma_f the mean sum_f w_f d_f / sum_f w_f with w_f = sigma_f^-2 is
        the maximum-likelihood range and reaches the Cramer-Rao bound, sigma = (sum_f w_f)^-1/2: at 12.5-31.25 MHz
        about 0.68 of the highest frequency's sd. A frequency without light (:meth:`dark`) weighs nothing in its
        pixel, and the consistency test has one degree of freedom fewer; a pixel with no frequency lit weighs them
        all. ``offsets_m`` (F,): each frequency's fixed depth offset relative to the highest [m], subtracted first;
        None: none. The noise scale moves the sds and the consistency test, not the mean. ``window``: each depth
        first has the integration window's leakage removed
        (:func:`~mpi_lidar.physics.window.window_corrections_m`), the offsets then being those that remain.
        """
        f = len(self.frequencies_hz)
        freqs = self.frequencies_hz
        window_m = window_corrections_m(raw[:, :f], raw[:, f:], freqs, self.sensor) if window else None
        offsets = np.zeros(f) if offsets_m is None else np.asarray(offsets_m, dtype=np.float64)
        dark = self.dark(raw[:, f:])
        # Summed column by column: a row reduction over F values is several times slower.
        metres_per_rad = self.metres_per_radian
        scale2 = self.noise_scale**2
        depths, weights = [], []
        top = int(np.argmax(freqs))
        for column in range(f):
            amplitude = np.maximum(raw[:, f + column].astype(np.float64), MIN_AMPLITUDE_V2)
            variance = scale2 * (self.read_variance_v4[column] + self.shot_variance_v2[column] * amplitude) \
                / amplitude**2
            weights.append(1.0 / (variance * metres_per_rad[column] ** 2))
            depth = raw[:, column].astype(np.float64) - offsets[column]
            depths.append(depth if window_m is None else depth + window_m[:, column])
        top_sigma = weights[top] ** -0.5
        dof = np.full(raw.shape[0], f - 1, dtype=np.int8)
        if dark is not None:
            rows, columns = dark
            for column in np.unique(columns):
                weights[column][rows[columns == column]] = 0.0
                depths[column][rows[columns == column]] = 0.0  # a dark frequency's depth may be NaN; it weighs 0
            np.subtract.at(dof, rows, 1)
        total = sum(weights[1:], weights[0])
        mean = sum((w * d for w, d in zip(weights[1:], depths[1:], strict=True)), weights[0] * depths[0]) / total
        chi2 = sum(w * (d - mean) ** 2 for w, d in zip(weights, depths, strict=True))
        with np.errstate(invalid="ignore"):  # rows without a finite depth: NaN chi2, not consistent
            consistent = chi2 <= _chi2_quantiles(f)[dof]
        return Fused(mean.astype(np.float32), (total**-0.5).astype(np.float32), top_sigma.astype(np.float32),
                     consistent, np.sqrt(chi2 / np.maximum(dof, 1)).astype(np.float32), dof)

    def dark(self, amplitude_v2: NDArray) -> tuple[NDArray[np.intp], NDArray[np.intp]] | None:
        """The (row, frequency) indices of the frequencies without light in amplitudes (n, F) [V^2], None where
        every frequency of every row has light. A frequency has light where its amplitude is above zero and at
        least ``NO_LIGHT_SIGMAS`` times its no-light noise (:attr:`floor_v2`) or ``LIT_SHARE`` of the row's highest
        such ratio (the frequencies of one return have alike amplitudes: where all are weak, none is dark); a row
        with no frequency lit has them all counted as lit."""
        floors = NO_LIGHT_SIGMAS * self.floor_v2
        dim = np.zeros(amplitude_v2.shape[0], bool)
        with np.errstate(invalid="ignore"):
            for column in range(amplitude_v2.shape[1]):  # column by column: most rows are lit everywhere
                dim |= ~(amplitude_v2[:, column] >= floors[column])
        rows = np.flatnonzero(dim)
        if not rows.size:
            return None
        with np.errstate(invalid="ignore", divide="ignore"):
            amplitude = amplitude_v2[rows].astype(np.float64)
            snr = amplitude / self.floor_v2[None, :]
            brightest = np.nanmax(np.where(np.isfinite(snr), snr, np.nan), axis=1, initial=0.0, keepdims=True)
            lit = ((snr >= NO_LIGHT_SIGMAS) | (snr >= LIT_SHARE * brightest)) & (amplitude > 0)
        lit |= ~lit.any(axis=1, keepdims=True)
        dark_rows, dark_columns = np.nonzero(~lit)
        return (rows[dark_rows], dark_columns) if dark_rows.size else None

    def chi2(self, raw: NDArray) -> NDArray[np.float64]:
        """chi^2 of each row's depths about their inverse-variance mean (n,): chi^2(F - 1) where they see one range
        (:attr:`Fused.dof` degrees of freedom where a frequency has no light)."""
        fused = self.fuse(raw)
        return np.maximum(fused.dof, 1) * fused.birge_ratio.astype(np.float64) ** 2

    def disagree(self, raw: NDArray, p_value: float) -> NDArray[np.bool_]:
        """Whether each row's depths (n,) disagree beyond chi-square's ``1 - p_value`` quantile at the row's own
        degrees of freedom (:attr:`Fused.dof`); a row with one lit frequency has nothing to disagree with."""
        return self.fuse(raw).disagree(p_value, len(self.frequencies_hz))


def noise_floor_v2(sensor: SensorConfig, frequencies_hz: tuple[float, ...]) -> NDArray[np.float64]:
    """Std of each tap quadrature with no light [V^2] of the default sensor's model (:attr:`NoiseModel.floor_v2`)."""
    return NoiseModel.for_sensor(sensor, frequencies_hz).floor_v2


def quadrature_noise_v2(sensor: SensorConfig, frequencies_hz: tuple[float, ...], amplitude_v2: NDArray) -> NDArray:
    """Std of a tap quadrature (n, F) [V^2] of the sensor's model (:meth:`NoiseModel.quadrature_sigma_v2`)."""
    return NoiseModel.for_sensor(sensor, frequencies_hz).quadrature_sigma_v2(amplitude_v2)


@lru_cache(maxsize=8)
def _quadrature_variance_line(sensor: SensorConfig, frequencies_hz: tuple[float, ...],
                              ) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Offset [V^4] and slope [V^2] per frequency (F,) of the moment model's quadrature variance against the
    amplitude: its variance at no light, and its growth per V^2 (at 1 V^2). The moment model's variance is a + b A
    in the amplitude A, so it is worked out at two amplitudes once per sensor."""
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
    """Std of the measured depth (n, F) [m] of the sensor's model (:meth:`NoiseModel.depth_sigma_m`)."""
    return NoiseModel.for_sensor(sensor, frequencies_hz).depth_sigma_m(amplitude_v2)


def unwrapped_rows(raw: NDArray, frequencies_hz: tuple[float, ...], sensor: SensorConfig,
                   ) -> tuple[NDArray[np.float32], NDArray[np.float64]]:
    """Raw rows (n, 2F) unwrapped by the sensor's model (:meth:`NoiseModel.unwrap`), and their confidence (n,)."""
    return NoiseModel.for_sensor(sensor, frequencies_hz).unwrap(raw)


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
    birge_ratio : sqrt(chi2 / dof), the spread of the frequencies over what the noise explains, (n,). [1]
    dof : The consistency test's degrees of freedom, the frequencies with light less one (F - 1 where all have
        light; :meth:`NoiseModel.dark`), (n,).
    """

    depth_m: NDArray[np.float32]
    sigma_m: NDArray[np.float32]
    top_sigma_m: NDArray[np.float32]
    consistent: NDArray[np.bool_]
    birge_ratio: NDArray[np.float32]
    dof: NDArray[np.int8]

    def disagree(self, p_value: float, frequencies: int) -> NDArray[np.bool_]:
        """Whether each row's depths (n,) of ``frequencies`` disagree beyond chi-square's ``1 - p_value`` quantile
        at the row's own degrees of freedom; a row with one lit frequency has nothing to disagree with."""
        dof = self.dof.astype(np.int64)
        with np.errstate(invalid="ignore"):
            return np.asarray(np.maximum(dof, 1) * self.birge_ratio.astype(np.float64) ** 2
                              > _chi2_quantiles(frequencies, p_value)[dof])


def fused_depths(raw: NDArray, frequencies_hz: tuple[float, ...], sensor: SensorConfig, *,
                 noise_scale: float = 1.0, offsets_m: NDArray | tuple[float, ...] | None = None,
                 window: bool = False) -> Fused:
    """The sensor's model's fused depths of raw rows (n, 2F) (:meth:`NoiseModel.fuse`)."""
    return NoiseModel.for_sensor(sensor, frequencies_hz, noise_scale).fuse(raw, offsets_m=offsets_m, window=window)


@lru_cache(maxsize=8)
def _chi2_quantiles(frequencies: int, p_value: float = FUSION_P_VALUE) -> NDArray[np.float64]:
    """The 1 - ``p_value`` quantile of chi-square with 0 to ``frequencies`` - 1 degrees of freedom (inf for none),
    indexed by the degrees of freedom."""
    from scipy.special import chdtri  # scipy.stats costs a second of imports; the special function does not

    return np.array([np.inf, *(chdtri(dof, p_value) for dof in range(1, max(frequencies, 1)))])
