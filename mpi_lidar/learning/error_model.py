"""The corrected depths' 1-sigma uncertainty: the model's own error, fitted on the validation rows of its training.

A corrected depth's error has two parts. What the model keeps of the measurement noise: on rows without
multipath it reaches the fused depth's sd, the Cramer-Rao bound of the four frequencies
(:func:`mpi_lidar.physics.noise.fused_depths`). And its error in the multipath it removes, which grows with the
size of the correction c (about as sqrt(|c|) for the default model: 2.2 mm at a 10 mm correction). So

.. math::

    \\sigma^2 = (a \\, \\sigma_{fused})^2 + \\left(s \\, (|c| / c_0)^p\\right)^2

with a, s and p fitted so that 68.27 % of the validation rows' errors lie within sigma (the share of a Gaussian
within one sd): the minimum of the pinball loss of that quantile of the absolute error. Validation rows were never
fitted by the booster, and their errors hold the simulated noise and the synthetic geometric inputs' estimation
error (:data:`mpi_lidar.learning.features.GEOMETRY_ERROR_MODEL`). docs/results/noise-limit.md checks the sigma on
held-out rows and on rendered scans.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from mpi_lidar.config import SensorConfig
from mpi_lidar.learning.model import UncertaintyCard
from mpi_lidar.physics.noise import fused_depths

# Share of a Gaussian's values within one sd of its mean: sigma is this quantile of the absolute error.
ONE_SIGMA_SHARE = 0.6827
# The correction at which the card states the model's own error [m]: a strong corner's typical correction.
REFERENCE_CORRECTION_M = 0.01
# Fewer validation rows than this fit no uncertainty model (the card then has none).
MIN_FIT_ROWS = 200
# The fit reads at most about this many rows, evenly spaced: the three parameters are settled long before.
MAX_FIT_ROWS = 200_000
# The exponent's bounds: from an error independent of the correction to one growing faster than it.
EXPONENT_BOUNDS = (0.0, 2.0)


def error_terms(raw: NDArray, depth_m: NDArray, true_depth_m: NDArray, frequencies_hz: tuple[float, ...],
                sensor: SensorConfig, noise_scale: float = 1.0) -> NDArray[np.float64]:
    """What the fit reads of rows (n, 2F) of unwrapped raw measurements [m, V^2] corrected to ``depth_m`` (n,)
    [m] whose true depth is ``true_depth_m`` (n,) [m]: columns (n, 3) of the fused depth's sd under the noise model
    (``noise_scale`` times the sensor's), the correction (corrected less the highest frequency's depth) and the
    error (corrected less true depth). [m]"""
    f = len(frequencies_hz)
    fused = fused_depths(raw, frequencies_hz, sensor, noise_scale=noise_scale)
    depth = np.asarray(depth_m, dtype=np.float64)
    return np.column_stack([fused.sigma_m.astype(np.float64), depth - raw[:, f - 1].astype(np.float64),
                            depth - np.asarray(true_depth_m, dtype=np.float64)])


def corrected_sigma_m(model: UncertaintyCard, fused_sigma_m: NDArray, correction_m: NDArray) -> NDArray[np.float64]:
    """1-sigma uncertainty [m] of corrected depths from their fused depth's sd (n,) [m] and their correction (n,)
    [m] (:class:`~mpi_lidar.learning.model.UncertaintyCard`)."""
    return _sigma_m(model.noise_factor, model.model_sd_m, model.correction_exponent,
                    np.asarray(fused_sigma_m, dtype=np.float64), np.asarray(correction_m, dtype=np.float64),
                    model.reference_correction_m)


def coverage(model: UncertaintyCard, terms: NDArray) -> float:
    """Share of rows (n, 3) of :func:`error_terms` whose error lies within their sigma. [1]"""
    return float((np.abs(terms[:, 2]) <= corrected_sigma_m(model, terms[:, 0], terms[:, 1])).mean())


def fit_uncertainty(terms: NDArray) -> UncertaintyCard | None:
    """The uncertainty model of validation rows (n, 3) of :func:`error_terms`: the parameters that minimise the
    pinball loss of the :data:`ONE_SIGMA_SHARE` quantile of the absolute error. None with fewer than
    :data:`MIN_FIT_ROWS` rows of finite terms."""
    from scipy.optimize import minimize  # only where a model is trained: scipy.optimize costs a second to import

    terms = terms[np.isfinite(terms).all(1)]
    if terms.shape[0] < MIN_FIT_ROWS:
        return None
    taken = terms[:: -(-terms.shape[0] // MAX_FIT_ROWS)]
    fused_sigma, correction, error = taken[:, 0], np.abs(taken[:, 1]), np.abs(taken[:, 2])

    def loss(parameters: NDArray) -> float:
        log_noise, log_model, exponent = parameters
        excess = error - _sigma_m(np.exp(log_noise), np.exp(log_model), exponent, fused_sigma, correction)
        return float(np.maximum(ONE_SIGMA_SHARE * excess, (ONE_SIGMA_SHARE - 1) * excess).mean())

    # Start from the noise alone at the Cramer-Rao bound and the rows' typical error for the model's part.
    start = np.array([0.0, np.log(max(float(np.quantile(error, ONE_SIGMA_SHARE)), 1e-9)), 0.5])
    bounds = [(-5.0, 5.0), (np.log(1e-9), np.log(10.0)), EXPONENT_BOUNDS]
    found = minimize(loss, start, method="Nelder-Mead", bounds=bounds,
                     options={"maxiter": 2000, "xatol": 1e-5, "fatol": 1e-12}).x
    noise_factor, model_sd_m, exponent = float(np.exp(found[0])), float(np.exp(found[1])), float(found[2])
    within = np.abs(terms[:, 2]) <= _sigma_m(noise_factor, model_sd_m, exponent, terms[:, 0], terms[:, 1])
    return UncertaintyCard(noise_factor=noise_factor, model_sd_m=model_sd_m,
                           reference_correction_m=REFERENCE_CORRECTION_M, correction_exponent=exponent,
                           validation_rows=int(terms.shape[0]),
                           validation_coverage=round(float(within.mean()), 4))


def _sigma_m(noise_factor: float, model_sd_m: float, exponent: float, fused_sigma_m: NDArray, correction_m: NDArray,
             reference_m: float = REFERENCE_CORRECTION_M) -> NDArray[np.float64]:
    """sigma [m]: the fused sd [m] times ``noise_factor`` and the model's own error, ``model_sd_m`` [m] at a
    correction of ``reference_m`` [m], growing as the absolute correction [m] to the ``exponent``."""
    model_part = model_sd_m * np.power(np.abs(correction_m) / reference_m, exponent)
    return np.hypot(noise_factor * fused_sigma_m, model_part)
