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

That law is fitted over the whole prior; a geometric model's error also depends on where in the prior a pixel's
inputs lie (a strong, distant partner leaves more of its multipath than a weak one). So a geometric model's
sigma is the law's times a factor per region of the prior (:func:`fit_region_scales`): bins of the equivalent
rho_ABA x d_AB the model read, each factor the 68.27 % quantile of the bin's validation errors in units of the
law's sigma, so that 68.27 % of every bin's rows lie within it. A pixel whose inputs lie beyond the prior's reach
takes the factor of the bin at the prior's edge and adds the share of its correction that the prior's reach
leaves out (:func:`beyond_prior_share`): an honest bound on what the model, which has not learned past the edge,
can miss.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from mpi_lidar.config import SensorConfig
from mpi_lidar.learning.model_card import RegionScales, UncertaintyCard
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
# The regions of the prior a geometric model's sigma is scaled in: bin edges of the equivalent rho_ABA [1] and of
# d_AB [m] (the last bins are open). Coarse enough that a quick training's validation rows fill most of them.
REGION_RHO_ABA_EDGES = (0.0, 0.05, 0.2, 0.5, 1.0)
REGION_D_AB_EDGES_M = (0.0, 0.1, 0.25)
# Fewer validation rows than this in a bin: it takes the factor of its rho_ABA row of bins, or 1 (the law alone).
MIN_REGION_ROWS = 30


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


def corrected_sigma_m(model: UncertaintyCard, fused_sigma_m: NDArray, correction_m: NDArray,
                      inputs: NDArray | None = None, reach: tuple[float, float] | None = None) -> NDArray[np.float64]:
    """1-sigma uncertainty [m] of corrected depths from their fused depth's sd (n,) [m] and their correction (n,)
    [m] (:class:`~mpi_lidar.learning.model_card.UncertaintyCard`).

    ``inputs`` (n, 2): the geometric inputs the model read, equivalent rho_ABA [1] and d_AB [m]; with them and a
    card with region scales, each row's sigma is scaled by its region's factor, and where ``reach`` (the prior's
    largest rho_ABA [1] and d_AB [m]) is given, rows beyond it add :func:`beyond_prior_share` of their correction.
    """
    correction = np.asarray(correction_m, dtype=np.float64)
    sigma = _sigma_m(model.noise_factor, model.model_sd_m, model.correction_exponent,
                     np.asarray(fused_sigma_m, dtype=np.float64), correction, model.reference_correction_m)
    if inputs is None:
        return sigma
    inputs = np.asarray(inputs, dtype=np.float64).reshape(-1, 2)
    if model.region_scales is not None:
        sigma = sigma * region_factor(model.region_scales, inputs)
    if reach is not None:
        sigma = np.hypot(sigma, beyond_prior_share(inputs, reach) * correction)
    return sigma


def region_factor(scales: RegionScales, inputs: NDArray) -> NDArray[np.float64]:
    """The factor (n,) [1] of each row's region of the prior, from its inputs (n, 2): rho_ABA [1], d_AB [m]
    (NaN or negative: the first bin)."""
    rho = np.nan_to_num(inputs[:, 0], nan=0.0)
    d_ab = np.nan_to_num(inputs[:, 1], nan=0.0)
    i = np.clip(np.searchsorted(scales.rho_aba_edges, rho, side="right") - 1, 0, len(scales.rho_aba_edges) - 1)
    j = np.clip(np.searchsorted(scales.d_ab_edges_m, d_ab, side="right") - 1, 0, len(scales.d_ab_edges_m) - 1)
    return np.asarray(scales.factors, dtype=np.float64)[i, j]


def beyond_prior(inputs: NDArray, reach: tuple[float, float]) -> NDArray[np.bool_]:
    """Rows (n,) whose inputs (n, 2), rho_ABA [1] and d_AB [m], lie beyond the prior's reach [1, m]."""
    return (inputs[:, 0] > reach[0]) | (inputs[:, 1] > reach[1])


def beyond_prior_share(inputs: NDArray, reach: tuple[float, float]) -> NDArray[np.float64]:
    """The share of a correction [1] that a model trained up to ``reach`` (its largest rho_ABA [1] and d_AB [m]) may
    leave out at inputs (n, 2), 0 inside the prior.

    The multipath bias grows about as rho_ABA x d_AB (small-phase limit), and past the prior's edge the trees
    predict what they learned at the edge: the correction of a pixel beyond it stands for at least the edge's
    strength, and the bias may be larger by the ratio of the pixel's strength to that, less one."""
    rho = np.nan_to_num(inputs[:, 0], nan=0.0)
    d_ab = np.nan_to_num(inputs[:, 1], nan=0.0)
    inside = np.minimum(rho, reach[0]) * np.minimum(d_ab, reach[1])
    with np.errstate(divide="ignore", invalid="ignore"):
        ratio = np.where(inside > 0, rho * d_ab / np.where(inside > 0, inside, 1.0), 1.0)
    return np.maximum(ratio - 1.0, 0.0)


def coverage(model: UncertaintyCard, terms: NDArray) -> float:
    """Share of rows (n, 3) of :func:`error_terms` whose error lies within their sigma; rows (n, 5) with the
    geometric inputs (rho_ABA, d_AB) in the last two columns take the card's region scales. [1]"""
    inputs = terms[:, 3:5] if terms.shape[1] >= 5 else None
    return float((np.abs(terms[:, 2]) <= corrected_sigma_m(model, terms[:, 0], terms[:, 1], inputs)).mean())


def fit_uncertainty(terms: NDArray) -> UncertaintyCard | None:
    """The uncertainty model of validation rows (n, 3) of :func:`error_terms`: the parameters that minimise the
    pinball loss of the :data:`ONE_SIGMA_SHARE` quantile of the absolute error. Rows (n, 5) that carry a geometric
    model's inputs (rho_ABA [1], d_AB [m]) in their last two columns also get the region scales
    (:func:`fit_region_scales`). None with fewer than :data:`MIN_FIT_ROWS` rows of finite terms."""
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
    # The simplex stops short on a flat loss (wide priors): the scale that puts exactly the share within is the
    # loss's minimum along the scale of both terms, so it is set exactly.
    fitted = _sigma_m(noise_factor, model_sd_m, exponent, fused_sigma, correction)
    scale = float(np.quantile(error / np.maximum(fitted, 1e-12), ONE_SIGMA_SHARE))
    noise_factor, model_sd_m = noise_factor * scale, model_sd_m * scale
    sigma = _sigma_m(noise_factor, model_sd_m, exponent, terms[:, 0], terms[:, 1])
    scales = None
    if terms.shape[1] >= 5:
        scales = fit_region_scales(np.abs(terms[:, 2]) / np.maximum(sigma, 1e-12), terms[:, 3:5])
        sigma = sigma * region_factor(scales, terms[:, 3:5])
    within = np.abs(terms[:, 2]) <= sigma
    return UncertaintyCard(noise_factor=noise_factor, model_sd_m=model_sd_m,
                           reference_correction_m=REFERENCE_CORRECTION_M, correction_exponent=exponent,
                           validation_rows=int(terms.shape[0]),
                           validation_coverage=round(float(within.mean()), 4), region_scales=scales)


def fit_region_scales(ratio: NDArray, inputs: NDArray, rho_aba_edges: tuple[float, ...] = REGION_RHO_ABA_EDGES,
                      d_ab_edges_m: tuple[float, ...] = REGION_D_AB_EDGES_M) -> RegionScales:
    """The factor per region of the prior: in each bin of rho_ABA [1] x d_AB [m] (lower edges; the last bins are
    open) of the rows' inputs (n, 2), the :data:`ONE_SIGMA_SHARE` quantile of their absolute errors in units of the
    law's sigma, ``ratio`` (n,) [1]. A bin with fewer than :data:`MIN_REGION_ROWS` rows takes its rho_ABA row's
    quantile, or 1 where that row has too few too."""
    rho_row = np.clip(np.searchsorted(rho_aba_edges, np.nan_to_num(inputs[:, 0]), side="right") - 1, 0, None)
    d_col = np.clip(np.searchsorted(d_ab_edges_m, np.nan_to_num(inputs[:, 1]), side="right") - 1, 0, None)
    factors = np.ones((len(rho_aba_edges), len(d_ab_edges_m)))
    for i in range(len(rho_aba_edges)):
        in_row = rho_row == i
        row_factor = (float(np.quantile(ratio[in_row], ONE_SIGMA_SHARE)) if in_row.sum() >= MIN_REGION_ROWS
                      else 1.0)
        for j in range(len(d_ab_edges_m)):
            in_bin = in_row & (d_col == j)
            factors[i, j] = (float(np.quantile(ratio[in_bin], ONE_SIGMA_SHARE)) if in_bin.sum() >= MIN_REGION_ROWS
                             else row_factor)
    return RegionScales(rho_aba_edges=rho_aba_edges, d_ab_edges_m=d_ab_edges_m,
                        factors=tuple(tuple(round(float(f), 4) for f in row) for row in factors))


def _sigma_m(noise_factor: float, model_sd_m: float, exponent: float, fused_sigma_m: NDArray, correction_m: NDArray,
             reference_m: float = REFERENCE_CORRECTION_M) -> NDArray[np.float64]:
    """sigma [m]: the fused sd [m] times ``noise_factor`` and the model's own error, ``model_sd_m`` [m] at a
    correction of ``reference_m`` [m], growing as the absolute correction [m] to the ``exponent``."""
    model_part = model_sd_m * np.power(np.abs(correction_m) / reference_m, exponent)
    return np.hypot(noise_factor * fused_sigma_m, model_part)
