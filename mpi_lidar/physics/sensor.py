"""APD/TIA detector chain (paper eq 16-30) and the waveform-level simulator.

The received light is sampled in bins of one carrier transit time (6 ns). In each bin the expected photon
count follows the two-path waveform (eq 1, 11); shot noise, avalanche gain with excess noise, dark current,
TIA and thermal noise turn it into a voltage (eq 30), which the 4-tap demodulator correlates (eq 4).

The calibration that makes Table I self-consistent: eq 4 gives Gamma = R alpha m / 2, so the received
voltage amplitude is R = 2 Gamma / (alpha m), and one photon in one bin yields
g = eta M q G / t_transit volts.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from mpi_lidar.config import Config, SensorConfig, SimulatorConfig
from mpi_lidar.constants import ELECTRON_VOLT_J
from mpi_lidar.physics import demod
from mpi_lidar.physics.transport import phasor, two_path_phasors


def photon_energy(planck_j_s: float, c: float, wavelength_m: float) -> float:
    """Energy of one photon, eq 17. [J]

    Parameters
    ----------
    planck_j_s : Planck constant. [J s]
    c : Speed of light. [m/s]
    wavelength_m : Laser wavelength. [m]
    """
    return planck_j_s * c / wavelength_m


def received_voltage_amplitude(gamma: ArrayLike, modulation_contrast: float, demod_amplitude_v: float):
    """Received voltage amplitude R from the correlation amplitude, inverting eq 4: R = 2 Gamma / (alpha m).

    Parameters
    ----------
    gamma : Amplitude of the cross correlation. [V^2]
    modulation_contrast : alpha of eq 1. [1]
    demod_amplitude_v : m of eq 2. [V]

    Returns
    -------
    R. [V]
    """
    return 2 * np.asarray(gamma, dtype=np.float64) / (modulation_contrast * demod_amplitude_v)


def received_power(photons_per_bin: ArrayLike, photon_energy_j: float, bin_s: float):
    """Optical power that delivers a photon count per bin, eq 16 solved for P_opt. [W]"""
    return np.asarray(photons_per_bin, dtype=np.float64) * photon_energy_j / bin_s


def thermal_noise_current(boltzmann_j_per_k: float, temperature_k: float, bandwidth_hz: float, load_ohm: float):
    """RMS thermal noise current of the load, eq 29. [A]"""
    return float(np.sqrt(4 * boltzmann_j_per_k * temperature_k * bandwidth_hz / load_ohm))


def tia_noise_electron_variance(transit_s: float, psd_a2_per_hz: float, bandwidth_hz: float, charge_c: float):
    """Variance of the TIA noise electrons per bin, eq 28. [electrons^2]"""
    return transit_s**2 * psd_a2_per_hz * bandwidth_hz / charge_c**2


def dark_electrons(sensor: SensorConfig) -> float:
    """Expected dark electrons per bin, eq 25 (the charge it gives, divided by q, then rounded).

    P_A I_FM T^{3/2} t exp(-E_g / 2 k_B T) is a charge; at Table I values it is ~1e-25 C, i.e. ~0 electrons.
    """
    s = sensor
    exponent = -s.bandgap_ev * ELECTRON_VOLT_J / (2 * s.boltzmann_j_per_k * s.temperature_k)
    charge = s.apd_area_m2 * s.dark_current_fom_a_per_m2 * s.temperature_k**1.5 * s.transit_time_s * np.exp(exponent)
    return float(np.round(charge / s.electron_charge_c))


@dataclass(frozen=True)
class DetectorChain:
    """Per-bin constants of the detector chain, derived once from the configuration.

    ``noise_scale`` multiplies every noise term's deviation from its mean (variances by its square), so
    noise_scale = 0 is the noiseless sensor and 1 is Table I.
    """

    volts_per_electron: float
    quantum_efficiency: float
    avalanche_gain: float
    excess_noise_factor: float
    dark_electrons: float
    tia_mean_electrons: float
    tia_electron_variance: float
    thermal_v_std: float
    background_mean_electrons: float
    background_std_electrons: float
    random_v_std: float
    noise_scale: float
    round_photons: bool

    @classmethod
    def from_config(cls, sensor: SensorConfig, simulator: SimulatorConfig) -> DetectorChain:
        s = sensor
        return cls(
            volts_per_electron=s.electron_charge_c * s.tia_gain_v_per_a / s.transit_time_s,  # eq 23-24
            quantum_efficiency=s.quantum_efficiency,
            avalanche_gain=s.avalanche_gain,
            excess_noise_factor=s.excess_noise_factor,
            dark_electrons=dark_electrons(s),
            tia_mean_electrons=simulator.tia_noise_mean_electrons,
            tia_electron_variance=tia_noise_electron_variance(
                s.transit_time_s, s.tia_noise_psd_a2_per_hz, s.bandwidth_hz, s.electron_charge_c
            ),
            thermal_v_std=thermal_noise_current(s.boltzmann_j_per_k, s.temperature_k, s.bandwidth_hz,
                                                s.load_resistance_ohm) * s.tia_gain_v_per_a,
            background_mean_electrons=simulator.background_mean_electrons,
            background_std_electrons=simulator.background_std_electrons,
            random_v_std=simulator.random_noise_std_v,
            noise_scale=simulator.noise_scale,
            round_photons=simulator.round_photons,
        )

    @property
    def volts_per_photon(self) -> float:
        """g = eta M q G / t_transit: mean voltage of one received photon in one bin. [V]"""
        return self.quantum_efficiency * self.avalanche_gain * self.volts_per_electron

    @property
    def offset_v(self) -> float:
        """Mean voltage of the signal-free terms: amplified background, dark and TIA electrons. [V]"""
        electrons = self.avalanche_gain * self.background_mean_electrons + self.dark_electrons
        return self.volts_per_electron * (electrons + self.tia_mean_electrons)

    @property
    def variance_per_photon_v2(self) -> float:
        """Voltage variance added per expected photon: Poisson (eq 18) then avalanche (eq 21). [V^2]

        Var = M^2 (eta^2 n + F eta n) electrons^2 for n photons: the spread of eta*n_shot, amplified, plus
        the excess noise of the avalanche given n_e.
        """
        e = self.quantum_efficiency
        per_photon = self.avalanche_gain**2 * e * (e + self.excess_noise_factor)
        return self.noise_scale**2 * self.volts_per_electron**2 * per_photon

    @property
    def signal_free_variance_v2(self) -> float:
        """Voltage variance of the terms that do not depend on the light: eq 19 background, 25-26, 27-29, 30.

        [V^2]
        """
        m = self.avalanche_gain
        electrons_var = (
            m**2 * self.background_std_electrons**2
            + m**2 * self.excess_noise_factor * self.background_mean_electrons
            + self.dark_electrons
            + self.tia_electron_variance
        )
        volts_var = self.volts_per_electron**2 * electrons_var + self.thermal_v_std**2 + self.random_v_std**2
        return self.noise_scale**2 * volts_var

    def bin_photons(self, expected: ArrayLike) -> NDArray[np.float64]:
        """Photon count per bin before shot noise, eq 16 (rounded when configured)."""
        x = np.asarray(expected, dtype=np.float64)
        return np.rint(x) if self.round_photons else x

    def bin_mean_voltage(self, photons: ArrayLike) -> NDArray[np.float64]:
        """Expected detector voltage of a bin holding ``photons`` (after eq 16 rounding), eq 30. [V]"""
        return self.volts_per_photon * np.asarray(photons, dtype=np.float64) + self.offset_v

    def bin_voltage_variance(self, photons: ArrayLike) -> NDArray[np.float64]:
        """Variance of the detector voltage of a bin holding ``photons``, eq 21, 26, 28, 29, 30. [V^2]"""
        return self.signal_free_variance_v2 + self.variance_per_photon_v2 * np.asarray(photons, dtype=np.float64)

    def sample_bin_voltage(self, photons: NDArray[np.float64], rng: np.random.Generator) -> NDArray[np.float64]:
        """One random detector voltage per bin, following the chain eq 18-30 step by step. [V]"""
        mean = self.bin_mean_voltage(photons)
        if self.noise_scale == 0:
            return mean
        shape = photons.shape
        n_shot = rng.poisson(np.maximum(photons, 0.0))  # eq 18
        background = self.background_mean_electrons + self.background_std_electrons * rng.standard_normal(shape)
        n_e = n_shot * self.quantum_efficiency + background  # eq 19
        avalanche_var = self.avalanche_gain**2 * self.excess_noise_factor * np.maximum(n_e, 0.0)  # eq 21
        n_apd = self.avalanche_gain * n_e + np.sqrt(avalanche_var) * rng.standard_normal(shape)  # eq 20, 22
        n_dark = rng.poisson(self.dark_electrons, shape) if self.dark_electrons > 0 else 0.0  # eq 26
        n_tia = self.tia_mean_electrons + np.sqrt(self.tia_electron_variance) * rng.standard_normal(shape)  # 27
        v_thermal = self.thermal_v_std * rng.standard_normal(shape)  # eq 29 times G
        v_rand = self.random_v_std * rng.standard_normal(shape) if self.random_v_std > 0 else 0.0
        voltage = self.volts_per_electron * (n_apd + n_dark + n_tia) + v_thermal + v_rand  # eq 23-24, 30
        return mean + self.noise_scale * (voltage - mean)


@dataclass(frozen=True)
class PhotonWaveform:
    """Expected photons per bin x(t) = X0 + Xc cos(w t) + Xs sin(w t), for samples of shape (n,)."""

    constant: NDArray[np.float64]
    cosine: NDArray[np.float64]
    sine: NDArray[np.float64]

    def at(self, wt: NDArray[np.float64]) -> NDArray[np.float64]:
        """Evaluate at phases wt (K,): shape (n, K). [photons]"""
        return self.constant[:, None] + self.cosine[:, None] * np.cos(wt) + self.sine[:, None] * np.sin(wt)

    @property
    def peak(self) -> NDArray[np.float64]:
        return self.constant + np.hypot(self.cosine, self.sine)


class SensorModel(ABC):
    """A simulator fidelity: scene parameters in, the four taps per frequency out.

    Contract: ``taps(theta, rng)`` takes theta of shape (n, 6) (d_AS, d_AB, rho_SAS, rho_SAB, rho_ABA,
    rho_BAS) and returns float64 taps of shape (n, F, 4) in V^2, for the configured frequencies in order, using
    only ``rng`` for randomness. ``multipath=False`` drops the A -> B -> A path. Every fidelity shares the
    detector chain and the window of :func:`demod.integration_bins`, so their taps agree in distribution.
    """

    def __init__(self, config: Config):
        self.config = config
        self.chain = DetectorChain.from_config(config.sensor, config.simulator)
        self.frequencies_hz = np.asarray(config.frequencies_hz, dtype=np.float64)
        s = config.sensor
        self.bins = [
            demod.integration_bins(s.integration_time_s, s.transit_time_s, f, config.simulator.whole_cycles)
            for f in config.frequencies_hz
        ]

    def photon_waveforms(self, theta: ArrayLike, multipath: bool = True) -> list[PhotonWaveform]:
        """Expected photons per bin of the two-path signal at each frequency, eq 1, 11-16."""
        s = self.config.sensor
        gamma_d, phi_d, gamma_m, phi_m = two_path_phasors(
            np.atleast_2d(theta), self.frequencies_hz, s.gamma_r_v2, s.speed_of_light_m_per_s, multipath
        )
        r_d = received_voltage_amplitude(gamma_d, s.modulation_contrast, s.demodulation_amplitude_v)
        r_m = received_voltage_amplitude(gamma_m, s.modulation_contrast, s.demodulation_amplitude_v)
        return self.waveforms_from_phasors(r_d + r_m, phasor(r_d, phi_d) + phasor(r_m, phi_m))

    def waveforms_from_phasors(self, dc_v: ArrayLike, phasor_v: ArrayLike) -> list[PhotonWaveform]:
        """Photon waveforms of any sum of paths, given per sample and frequency (n, F).

        A sum of paths R_k (1 + alpha cos(w t - phi_k)) has the constant part sum R_k = ``dc_v`` and the
        oscillating part alpha Re(sum R_k e^{j phi_k} e^{-j w t}), with ``phasor_v`` = sum R_k e^{j phi_k}
        (the sign convention of :mod:`mpi_lidar.physics.transport`).

        Parameters
        ----------
        dc_v : Sum of the received voltage amplitudes of all paths, shape (n, F). [V]
        phasor_v : Sum of R_k e^{j phi_k}, complex, shape (n, F). [V]
        """
        to_photons = 1.0 / self.chain.volts_per_photon
        dc = np.atleast_2d(np.asarray(dc_v, dtype=np.float64)) * to_photons
        phasor = np.atleast_2d(np.asarray(phasor_v, dtype=np.complex128)) * to_photons
        alpha = self.config.sensor.modulation_contrast
        return [
            PhotonWaveform(constant=dc[:, j], cosine=alpha * phasor[:, j].real, sine=alpha * phasor[:, j].imag)
            for j in range(self.frequencies_hz.size)
        ]

    def phases(self, j: int) -> NDArray[np.float64]:
        """w t_i over the integration window of frequency j. [rad]"""
        return 2 * np.pi * self.frequencies_hz[j] * demod.bin_times(self.bins[j], self.config.sensor.transit_time_s)

    @abstractmethod
    def sample_taps(self, waveforms: list[PhotonWaveform], rng: np.random.Generator) -> NDArray[np.float64]:
        """Random taps for given photon waveforms (one per frequency), shape (n, F, 4). [V^2]"""

    def taps(self, theta: ArrayLike, rng: np.random.Generator, multipath: bool = True) -> NDArray[np.float64]:
        """Random taps of two-path scenes, shape (n, F, 4). [V^2]"""
        return self.sample_taps(self.photon_waveforms(theta, multipath), rng)

    def taps_from_phasors(self, dc_v: ArrayLike, phasor_v: ArrayLike, rng: np.random.Generator) -> NDArray:
        """Random taps of arbitrary light (e.g. a rendered scene), see :meth:`waveforms_from_phasors`. [V^2]"""
        return self.sample_taps(self.waveforms_from_phasors(dc_v, phasor_v), rng)

    def measure(
        self, theta: ArrayLike, rng: np.random.Generator, multipath: bool = True
    ) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """Depth [m] and amplitude [V^2] per sample and frequency, shape (n, F) each, eq 5-7."""
        return demod.depth_and_amplitude(
            self.taps(theta, rng, multipath), self.frequencies_hz, self.config.sensor.speed_of_light_m_per_s
        )


class WaveformSensor(SensorModel):
    """Faithful simulator: draws every bin's voltage through the chain, then correlates the four taps.

    Cost grows with the number of bins (2667 per frequency), about 100x the moment-matched simulator.
    """

    batch_rows = 256

    def sample_taps(self, waveforms: list[PhotonWaveform], rng: np.random.Generator) -> NDArray[np.float64]:
        n = waveforms[0].constant.size
        out = np.empty((n, self.frequencies_hz.size, 4))
        bin_s = self.config.sensor.transit_time_s
        m = self.config.sensor.demodulation_amplitude_v
        for start in range(0, n, self.batch_rows):
            rows = slice(start, start + self.batch_rows)
            for j, waveform in enumerate(waveforms):
                part = PhotonWaveform(waveform.constant[rows], waveform.cosine[rows], waveform.sine[rows])
                photons = self.chain.bin_photons(part.at(self.phases(j)))
                voltage = self.chain.sample_bin_voltage(photons, rng)
                out[rows, j] = demod.correlate_taps(voltage, self.frequencies_hz[j], bin_s, m)
        return out
