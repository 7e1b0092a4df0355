"""Two-path light transport of the coaxial scanning LiDAR (paper eq 11-15).

The beam hits point A; the direct path returns A -> S, the multipath returns A -> B -> A -> S. Both reach
the detector as phasors of the cross correlation at each modulation frequency.

Phasor sign convention (the package's only one): a path of one-way length d, which the light travels
twice, reaches the detector at modulation frequency f as the phasor

    amplitude * exp(+1j * 4 pi f d / c) = amplitude * exp(+1j * phi),    phi = round-trip phase (eq 14, 15),

built by :func:`path_phasor` (or :func:`phasor` from a phase). The received signal of a sum of paths is
sum_k R_k (1 + alpha cos(w t - phi_k)), whose oscillating part is alpha Re(sum_k R_k e^{+j phi_k} e^{-j w t}),
and the 4-tap demodulation (eq 5) returns arg(sum_k R_k e^{+j phi_k}) as the phase: a single path's
phasor angle is its phase delay, and its depth is c angle / (4 pi f). Everything that forms phasors (the
simulators, the scene renderer, the two-path inverse solvers) follows this convention.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray


def direct_amplitude(gamma_r: float, rho_sas: ArrayLike, d_as: ArrayLike) -> NDArray[np.float64]:
    """Amplitude of the direct path's cross correlation, eq 12.

    Parameters
    ----------
    gamma_r : Initial value of the cross correlation. [V^2]
    rho_sas : BRDF from S to S through A. [1]
    d_as : Distance from the sensor to A. [m]
    """
    return gamma_r * np.asarray(rho_sas, dtype=np.float64) / np.asarray(d_as, dtype=np.float64) ** 2


def multipath_amplitude(
    gamma_r: float, rho_sab: ArrayLike, rho_aba: ArrayLike, rho_bas: ArrayLike, d_as: ArrayLike
) -> NDArray[np.float64]:
    """Amplitude of the A -> B -> A path's cross correlation, eq 13.

    Parameters
    ----------
    gamma_r : Initial value of the cross correlation. [V^2]
    rho_sab, rho_aba, rho_bas : BRDFs of the three reflections. [1]
    d_as : Distance from the sensor to A. [m]
    """
    product = np.asarray(rho_sab, dtype=np.float64) * np.asarray(rho_aba) * np.asarray(rho_bas)
    return gamma_r * product / np.asarray(d_as, dtype=np.float64) ** 2


def round_trip_phase(frequency_hz: ArrayLike, path_m: ArrayLike, c: float) -> NDArray[np.float64]:
    """Phase delay of a path, eq 14 (path = d_AS) and eq 15 (path = d_AS + d_AB), not wrapped.

    Parameters
    ----------
    frequency_hz : Modulation frequency. [Hz]
    path_m : One-way length of the path; the light travels it twice. [m]
    c : Speed of light. [m/s]
    """
    return 4 * np.pi * np.asarray(frequency_hz, dtype=np.float64) * np.asarray(path_m, dtype=np.float64) / c


def phasor(amplitude: ArrayLike, phase_rad: ArrayLike) -> NDArray[np.complex128]:
    """The phasor amplitude * exp(+1j * phase) of a path whose round-trip phase is known (the convention).

    Parameters
    ----------
    amplitude : Amplitude of the path (of the cross correlation [V^2], or of the received voltage [V]).
    phase_rad : Round-trip phase delay of the path, see :func:`round_trip_phase`. [rad]

    Returns
    -------
    Complex phasor, shape of the broadcast arguments, in the unit of ``amplitude``.
    """
    return np.asarray(amplitude, dtype=np.float64) * np.exp(1j * np.asarray(phase_rad, dtype=np.float64))


def path_phasor(amplitude: ArrayLike, depth_m: ArrayLike, frequency_hz: ArrayLike, c: float
                ) -> NDArray[np.complex128]:
    """The phasor amplitude * exp(+1j * 4 pi f d / c) of a path of one-way length d (the convention).

    Parameters
    ----------
    amplitude : Amplitude of the path (of the cross correlation [V^2], or of the received voltage [V]).
    depth_m : One-way length d of the path; the light travels it twice. [m]
    frequency_hz : Modulation frequency f, broadcast against ``depth_m``. [Hz]
    c : Speed of light. [m/s]

    Returns
    -------
    Complex phasor, shape of the broadcast arguments, in the unit of ``amplitude``.
    """
    return phasor(amplitude, round_trip_phase(frequency_hz, depth_m, c))


# Largest multiple of a common base frequency whose phasor :func:`phasor_sums` takes as a power of the base's.
MAX_HARMONIC = 8


def harmonic_multiples(frequencies_hz: ArrayLike) -> tuple[float, NDArray[np.int64]] | None:
    """(f0, m (F,)) with every frequency m f0 for small whole m (at most :data:`MAX_HARMONIC`), or None; f0 in the
    frequencies' unit (Hz, or rad/m of wavenumbers).

    The sensor's 12.5, 18.75, 25 and 31.25 MHz are 2, 3, 4 and 5 times 6.25 MHz."""
    freqs = np.asarray(frequencies_hz, dtype=np.float64).ravel()
    if freqs.size == 0 or np.any(freqs <= 0):
        return None
    for divisor in range(1, MAX_HARMONIC + 1):
        base = freqs.min() / divisor
        multiples = np.rint(freqs / base)
        if multiples.max() <= MAX_HARMONIC and np.allclose(freqs, multiples * base, rtol=1e-12, atol=0):
            return base, multiples.astype(np.int64)
    return None


def phasor_sums(weights: ArrayLike, depth_m: ArrayLike, frequencies_hz: ArrayLike, c: float
                ) -> NDArray[np.complex128]:
    """sum_j w_j path_phasor(1, d_j, f) over the last axis of weights and one-way path lengths (..., J) [1, m],
    at every frequency (F,) [Hz]: shape (..., F), in the unit of the weights.

    Where the frequencies are small multiples of a common one (:func:`harmonic_multiples`), each frequency's
    phasors are powers of that one's: one complex exponential instead of F, the bulk of a scene render's time.
    The sums then differ from those of F exponentials by a few units in the last place."""
    weights = np.asarray(weights, dtype=np.float64)
    depth = np.asarray(depth_m, dtype=np.float64)
    freqs = np.asarray(frequencies_hz, dtype=np.float64)
    harmonics = harmonic_multiples(freqs)
    if harmonics is None:
        return np.einsum("...j,...jf->...f", weights, path_phasor(1.0, depth[..., None], freqs, c))
    base_hz, multiples = harmonics
    unit = path_phasor(1.0, depth, base_hz, c)
    sums = np.zeros((*np.broadcast_shapes(weights.shape, depth.shape)[:-1], freqs.size), dtype=np.complex128)
    term = weights * unit
    for m in range(1, int(multiples.max()) + 1):
        if m > 1:
            term *= unit
        if np.any(multiples == m):
            sums[..., multiples == m] = term.sum(-1)[..., None]
    return sums


def two_path_phasors(
    theta: NDArray[np.float64], frequencies_hz: ArrayLike, gamma_r: float, c: float, multipath: bool = True
) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
    """Direct and multipath amplitudes and phases for each sample and frequency, eq 12-15.

    The phasors of the two paths are :func:`phasor` (gamma_d, phi_d) and :func:`phasor` (gamma_m, phi_m).

    Parameters
    ----------
    theta : Scene parameters, shape (n, 6), columns (d_AS [m], d_AB [m], rho_SAS, rho_SAB, rho_ABA, rho_BAS).
    frequencies_hz : Modulation frequencies, shape (F,). [Hz]
    gamma_r : Initial value of the cross correlation. [V^2]
    c : Speed of light. [m/s]
    multipath : False drops the A -> B -> A path (its amplitude becomes 0).

    Returns
    -------
    gamma_d, phi_d, gamma_m, phi_m : each shape (n, F); amplitudes [V^2], phases [rad].
    """
    d_as, d_ab, rho_sas, rho_sab, rho_aba, rho_bas = np.asarray(theta, dtype=np.float64).T
    freqs = np.asarray(frequencies_hz, dtype=np.float64)[None, :]
    gamma_d = np.broadcast_to(direct_amplitude(gamma_r, rho_sas, d_as)[:, None], (d_as.size, freqs.size))
    gamma_m = multipath_amplitude(gamma_r, rho_sab, rho_aba, rho_bas, d_as)[:, None] * float(multipath)
    gamma_m = np.broadcast_to(gamma_m, gamma_d.shape)
    phi_d = round_trip_phase(freqs, d_as[:, None], c)
    phi_m = round_trip_phase(freqs, (d_as + d_ab)[:, None], c)
    return gamma_d, phi_d, gamma_m, phi_m


def two_path_phase_bias(ratio: ArrayLike, delta_phase: ArrayLike) -> NDArray[np.float64]:
    """Phase error that the multipath adds to the direct phase (closed form of eq 11).

    arg(1 + r e^{j dphi}) = atan(r sin(dphi) / (1 + r cos(dphi))), taken with atan2 so r > 1 stays right.

    Parameters
    ----------
    ratio : Gamma_M / Gamma_D. [1]
    delta_phase : phi_M - phi_D. [rad]
    """
    r = np.asarray(ratio, dtype=np.float64)
    dphi = np.asarray(delta_phase, dtype=np.float64)
    return np.arctan2(r * np.sin(dphi), 1 + r * np.cos(dphi))
