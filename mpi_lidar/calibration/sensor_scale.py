"""A scan's amplitude units, noise scale and per-frequency depth offsets, measured on its own flat surfaces.

A scanner reports amplitude in its own units, ``amplitude_units = amplitude_scale x amplitude_V2``; its depth
noise may differ from the noise model (:func:`mpi_lidar.physics.noise.depth_noise_m`) by a factor, the noise
scale eta; and each frequency may read every depth a fixed offset o_f too far. On a flat surface without
multipath, a frequency's depth minus the surface's plane is that frequency's noise plus its offset, so

    r_f ~ mu_f + eta sd_f(A_f / lambda),

with lambda the amplitude scale [units / V^2] and A_f the amplitude the scanner reports. The noise model's shape
tells lambda from eta: the thermal and TIA noise are constant, so at low amplitude sd ~ 1 / A (only the product
lambda eta is seen there), while shot noise grows with the signal, so at high amplitude sd ~ 1 / sqrt(A) (only
lambda eta^2). A scan whose amplitudes span both regimes measures both; where they span one, only a product is
determined, and :class:`SensorScale` says so.

Residuals. :mod:`mpi_lidar.calibration.flat_residuals` gives them, from planes fitted to the mean depth over the
frequencies, with each pixel's leverage h_i: the residual variance is then (S1) of that module,
Var r_f = s_f^2 (1 - 2 h_i / F) + h_i / F^2 sum_g s_g^2, and :func:`estimate_sensor_scale` uses (S1), not s_f^2.

Offsets. The plane takes up the offsets' mean, so the residuals show mu_f = o_f - mean_g o_g: only differences
between frequencies are measured, and :attr:`SensorScale.offsets_m` gives them relative to the highest frequency.

Fit. Maximum likelihood of the residuals under a Student-t of six degrees of freedom (``STUDENT_DOF``) and scale
k eta sqrt(S1): plane leftovers, flying pixels at edges and wrapped frequencies weigh less than under a Gaussian.
k (:func:`gaussian_t_scale`) makes eta the standard deviation's factor where the noise is Gaussian. The parameters
are log lambda, log eta and mu_f; the model's sd_f is tabulated once on a log grid of amplitudes. The covariance
is the sandwich H^-1 J H^-1 of the per-pixel scores (the t is a working model, the noise Gaussian).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from mpi_lidar.calibration._likelihood import Likelihood, gaussian_t_scale
from mpi_lidar.calibration.flat_residuals import MAX_PIXELS, flat_surface_residuals
from mpi_lidar.config import SensorConfig
from mpi_lidar.correction.options import CorrectionOptions
from mpi_lidar.correction.scene import SceneGeometry
from mpi_lidar.scans.scan import Scan

# A scale is significant where its relative standard deviation is at most this.
MAX_RELATIVE_SIGMA = 0.1

__all__ = ["MIN_PIXELS", "OUTLIER_ROUNDS", "SensorScale", "estimate_sensor_scale", "gaussian_t_scale",
           "measure_sensor_scale"]

# A measurement is significant with at least this many pixels and the amplitude scale (and a fitted noise scale)
# known to MAX_RELATIVE_SIGMA, the relative standard deviation the amplitude unit's reading is held to.
MIN_PIXELS = 200
# At most this many rounds of fits leave outliers out (the likelihood's OUTLIER_SIGMAS).
OUTLIER_ROUNDS = 3


@dataclass(frozen=True)
class SensorScale:
    """What a scan's flat surfaces say of its amplitude units, noise and depth offsets (:func:`estimate_sensor_scale`).

    Attributes
    ----------
    amplitude_scale : float
        lambda: the scanner's amplitude unit per V^2 of the noise model, NaN where nothing was measured. [units/V^2]
    amplitude_scale_sigma : float
        Its standard deviation, inf where it is not determined. [units/V^2]
    noise_scale : float
        eta: the depth noise over the noise model's (the fixed value where it was fixed). [1]
    noise_scale_sigma : float
        Its standard deviation (0 where fixed, inf where not determined). [1]
    offsets_m : NDArray[np.float64]
        Depth offset of each frequency (F,) relative to the highest frequency (whose entry is 0): a common offset
        of all frequencies is taken up by the planes and cannot be measured. [m]
    offsets_sigma_m : NDArray[np.float64]
        Their standard deviations (F,). [m]
    pixels : int
        Pixels the fit used.
    significant : bool
        Whether the amplitude scale (and a fitted noise scale) is known to ``MAX_RELATIVE_SIGMA`` on at least
        ``MIN_PIXELS`` pixels.
    reason : str
        Why it is not significant; empty where it is.
    scale_noise_correlation : float
        Correlation of log amplitude_scale and log noise_scale: near 1 in magnitude where only a product of them
        is determined. [1]
    amplitude_decades : float
        log10 of the 95th over the 5th percentile of the pixels' amplitudes: the span that tells the two scales
        apart. [1]
    outliers : int
        Pixels left out for a residual beyond five standard deviations (the likelihood's ``OUTLIER_SIGMAS``).
    """

    amplitude_scale: float
    amplitude_scale_sigma: float
    noise_scale: float
    noise_scale_sigma: float
    offsets_m: NDArray[np.float64]
    offsets_sigma_m: NDArray[np.float64]
    pixels: int
    significant: bool
    reason: str
    scale_noise_correlation: float = float("nan")
    amplitude_decades: float = float("nan")
    outliers: int = 0


def measure_sensor_scale(scan: Scan, usable_depth: NDArray, options: CorrectionOptions, sensor: SensorConfig, *,
                         scene: SceneGeometry | None = None, fix_noise_scale: float | None = None,
                         window: bool = False) -> SensorScale:
    """The amplitude scale, noise scale and depth offsets of a scan, from its flat surfaces.

    :func:`~mpi_lidar.calibration.flat_residuals.flat_surface_residuals`, then :func:`estimate_sensor_scale`.

    Parameters
    ----------
    scan : Scan
        The scan (its maps may stay in the store).
    usable_depth : NDArray
        Highest-frequency depth (H*W,) of the usable pixels, NaN elsewhere; from the depths alone where the
        amplitude's unit is not known. [m]
    options : CorrectionOptions
        Block size, partner range, footprint and tile size of the scene geometry.
    sensor : SensorConfig
        The sensor whose noise model the noise is scaled from.
    scene : SceneGeometry | None
        The scan's scene geometry where it was analysed already (its blocks and surfaces are used).
    fix_noise_scale : float | None
        Hold the noise scale at this value (:func:`estimate_sensor_scale`). [1]
    window : bool
        Measure the depths with the integration window's leakage removed
        (:func:`~mpi_lidar.physics.window.window_corrections_m`, which reads the amplitudes in V^2).

    Returns
    -------
    SensorScale
        The estimates, their standard deviations, and whether they are significant.
    """
    flat = flat_surface_residuals(scan, usable_depth, options, scene=scene, window_sensor=sensor if window else None)
    return estimate_sensor_scale(flat.amplitude, flat.residual_m, scan.frequencies_hz, sensor,
                                 fix_noise_scale=fix_noise_scale, leverage=flat.leverage)


def estimate_sensor_scale(amplitude: NDArray, residual_m: NDArray, frequencies_hz: tuple[float, ...],
                          sensor: SensorConfig, *, fix_noise_scale: float | None = None,
                          leverage: NDArray | None = None) -> SensorScale:
    """Maximum-likelihood amplitude scale, noise scale and depth offsets of flat-surface residuals.

    Parameters
    ----------
    amplitude : NDArray
        Amplitude (n, F) as the scanner reports it. [scanner units]
    residual_m : NDArray
        Depth minus the surface's plane (n, F) of pixels without multipath. [m]
    frequencies_hz : tuple[float, ...]
        The F modulation frequencies, in the columns' order. [Hz]
    sensor : SensorConfig
        The sensor whose noise model (:func:`~mpi_lidar.physics.noise.depth_noise_m`) the noise is scaled
        from.
    fix_noise_scale : float | None
        Hold the noise scale at this value and fit only the amplitude scale and offsets: where the amplitudes span
        one noise regime only, this gives the amplitude scale the product determines. [1]
    leverage : NDArray | None
        The leverage (n,) of each pixel in the plane fit over the mean depth of the frequencies
        (:attr:`~mpi_lidar.calibration.flat_residuals.FlatSurfaceResiduals.leverage`), for (S1); None: residuals
        from the true plane. [1]

    Returns
    -------
    SensorScale
        The estimates, their standard deviations, and whether they are significant.
    """
    if fix_noise_scale is not None and not (np.isfinite(fix_noise_scale) and fix_noise_scale > 0):
        raise ValueError(f"fix_noise_scale must be a positive number, got {fix_noise_scale}")
    freqs = tuple(float(f) for f in frequencies_hz)
    amplitude, residual, lever = _usable_rows(amplitude, residual_m, leverage, len(freqs))
    order = np.argsort(freqs)
    if amplitude.shape[0] < MIN_PIXELS:
        return _nothing_measured(len(freqs), amplitude.shape[0], fix_noise_scale,
                                 f"only {amplitude.shape[0]} flat pixels, at least {MIN_PIXELS} needed")
    outliers = 0
    for _ in range(OUTLIER_ROUNDS + 1):
        model = Likelihood(np.log(amplitude), residual, lever, freqs, sensor, fix_noise_scale)
        theta, converged = model.fit()
        outlying = model.outlying(theta)
        if not outlying.any():
            break
        # Gross outliers still pull the bounded-influence fit, and all the more the split of lambda from eta where
        # they gather at one end of the amplitudes: they are dropped and the fit repeated.
        outliers += int(outlying.sum())
        amplitude, residual, lever = amplitude[~outlying], residual[~outlying], lever[~outlying]
        if amplitude.shape[0] < MIN_PIXELS:
            return _nothing_measured(len(freqs), amplitude.shape[0], fix_noise_scale,
                                     f"only {amplitude.shape[0]} flat pixels once {outliers} outliers were left out, "
                                     f"at least {MIN_PIXELS} needed")
    covariance = model.covariance(theta)
    return _result(model, theta, covariance, converged, order[-1], _decades(amplitude), amplitude.shape[0], outliers)


def _usable_rows(amplitude: NDArray, residual_m: NDArray, leverage: NDArray | None, frequencies: int
                 ) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
    """The rows with finite residuals and finite positive amplitudes, at most ``MAX_PIXELS`` evenly spaced."""
    amplitude = np.asarray(amplitude, dtype=np.float64).reshape(-1, frequencies)
    residual = np.asarray(residual_m, dtype=np.float64).reshape(-1, frequencies)
    if amplitude.shape != residual.shape:
        raise ValueError(f"amplitude {amplitude.shape} and residual_m {residual.shape} must have the same shape")
    lever = np.zeros(amplitude.shape[0]) if leverage is None else np.asarray(leverage, dtype=np.float64).ravel()
    if lever.shape != (amplitude.shape[0],):
        raise ValueError(f"leverage must have one value per row ({amplitude.shape[0]}), got {lever.shape}")
    with np.errstate(invalid="ignore"):
        good = (np.isfinite(residual).all(1) & np.isfinite(amplitude).all(1) & (amplitude > 0).all(1)
                & np.isfinite(lever) & (lever >= 0) & (lever < 1))
    rows = np.flatnonzero(good)
    if rows.size > MAX_PIXELS:  # evenly spaced, so every part of the scan keeps its share
        rows = rows[np.linspace(0, rows.size - 1, MAX_PIXELS).round().astype(np.intp)]
    return amplitude[rows], residual[rows], lever[rows]


def _decades(amplitude: NDArray) -> float:
    """log10 of the 95th over the 5th percentile of all amplitudes (n, F). [1]"""
    low, high = np.percentile(amplitude, [5, 95])
    return float(np.log10(high / low))


def _result(model: Likelihood, theta: NDArray, covariance: NDArray, converged: bool, reference: int,
            decades: float, pixels: int, outliers: int) -> SensorScale:
    """The :class:`SensorScale` of a fit: estimates, standard deviations, and whether they are significant."""
    log_scale, log_noise, offsets = model.split(theta)
    frequencies = offsets.size
    first_offset = 2 if model.fits_noise else 1
    # Offsets relative to the reference (highest) frequency: difference vectors through the covariance.
    contrast = np.zeros((frequencies, theta.size))
    contrast[:, first_offset:first_offset + frequencies] = np.diag(model.unit_m)
    contrast[:, first_offset + reference] -= model.unit_m[reference]
    offset_variance = np.einsum("ij,jk,ik->i", contrast, covariance, contrast)
    scale_sd = float(np.sqrt(covariance[0, 0]))
    noise_sd = float(np.sqrt(covariance[1, 1])) if model.fits_noise else 0.0
    correlation = float("nan")
    if model.fits_noise and np.isfinite(scale_sd * noise_sd) and scale_sd * noise_sd > 0:
        correlation = float(covariance[0, 1] / (scale_sd * noise_sd))
    at_bound = abs(log_scale - model.bounds[0][0]) < 1e-3 or abs(log_scale - model.bounds[0][1]) < 1e-3
    if at_bound:  # the likelihood still rises beyond the searched range: the scale is not determined
        scale_sd = float("inf")
    reason = _reason(model, theta, covariance, converged, at_bound, scale_sd, noise_sd, decades)
    return SensorScale(
        amplitude_scale=float(np.exp(log_scale)), amplitude_scale_sigma=float(np.exp(log_scale) * scale_sd),
        noise_scale=float(np.exp(log_noise)), noise_scale_sigma=float(np.exp(log_noise) * noise_sd),
        offsets_m=offsets - offsets[reference], offsets_sigma_m=np.sqrt(np.maximum(offset_variance, 0.0)),
        pixels=pixels, significant=not reason, reason=reason, scale_noise_correlation=correlation,
        amplitude_decades=decades, outliers=outliers)


def _reason(model: Likelihood, theta: NDArray, covariance: NDArray, converged: bool, at_bound: bool,
            scale_sd: float, noise_sd: float, decades: float) -> str:
    """Why a fit is not significant ("" where it is)."""
    if not converged:
        return "the likelihood fit did not converge"
    if scale_sd <= MAX_RELATIVE_SIGMA and noise_sd <= MAX_RELATIVE_SIGMA:
        return ""
    span = f"the flat pixels' amplitudes span {decades:.2f} decades (5-95 %)"
    if model.fits_noise and at_bound:
        return (f"{span}: the likelihood keeps rising to the edge of the searched amplitude scales, so only a "
                "product of amplitude scale and noise scale is determined; fix the noise scale (fix_noise_scale=1) "
                "to read the amplitude scale")
    if model.fits_noise and np.isfinite(covariance[:2, :2]).all():
        power, product_sd = _best_determined_product(covariance)
        if product_sd <= MAX_RELATIVE_SIGMA:
            product = float(np.exp(power * theta[0] + theta[1]))
            return (f"{span}, too narrow to tell the amplitude scale from the noise scale (relative sigmas "
                    f"{scale_sd:.2g} and {noise_sd:.2g}): only amplitude_scale^{power:.2f} x noise_scale is "
                    f"determined, {product:.4g} to {product_sd:.2g}; fix the noise scale (fix_noise_scale=1) to read "
                    "the amplitude scale")
    return (f"the amplitude scale is known only to {scale_sd:.2g} (relative sigma; noise scale {noise_sd:.2g}), "
            f"more than {MAX_RELATIVE_SIGMA:g}: too few or too noisy flat pixels, or {span}")


def _best_determined_product(covariance: NDArray) -> tuple[float, float]:
    """The power p of lambda^p eta best determined by the fit, and that product's relative standard deviation.

    Var(p log lambda + log eta) = p^2 V_ll + 2 p V_le + V_ee is least at p = -V_le / V_ll: p = 1 where the noise is
    thermal (sd ~ lambda eta / A), 1/2 where it is shot noise (sd ~ eta sqrt(lambda / A)).
    """
    v_ll, v_le, v_ee = covariance[0, 0], covariance[0, 1], covariance[1, 1]
    power = -v_le / v_ll
    return float(power), float(np.sqrt(max(v_ee - v_le**2 / v_ll, 0.0)))


def _nothing_measured(frequencies: int, pixels: int, fix_noise_scale: float | None, reason: str) -> SensorScale:
    """The :class:`SensorScale` of too few pixels: NaN estimates, infinite standard deviations."""
    return SensorScale(
        amplitude_scale=float("nan"), amplitude_scale_sigma=float("inf"),
        noise_scale=float("nan") if fix_noise_scale is None else float(fix_noise_scale),
        noise_scale_sigma=float("inf") if fix_noise_scale is None else 0.0,
        offsets_m=np.full(frequencies, np.nan), offsets_sigma_m=np.full(frequencies, np.inf), pixels=pixels,
        significant=False, reason=reason)

