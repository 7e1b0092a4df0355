"""The uncertainty stage: each depth's 1-sigma, from the noise model, the multipath the scene geometry expects,
and for a corrected depth the model's own error and the footprint estimate's."""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from mpi_lidar.correction.footprint import FootprintEstimate
from mpi_lidar.learning.error_model import corrected_sigma_m
from mpi_lidar.learning.model import ModelCard
from mpi_lidar.physics.noise import Fused


def measured_sigma_m(fused: Fused) -> NDArray[np.float32]:
    """The sd of the highest frequency's measured depth (n,) [m]: its noise, widened by the frequencies' Birge
    ratio where they disagree beyond their noise (multipath that differs between them, a flying pixel)."""
    return fused.top_sigma_m * np.where(fused.consistent, 1.0, fused.birge_ratio)


def left_alone_sigma_m(sigma_m: NDArray, expected_bias_m: NDArray) -> NDArray[np.float64]:
    """1-sigma of a depth the model left alone (n,) [m]: its sd (n,) [m] combined with the multipath bias the scene
    geometry expects there (n,) [m], below the gate's threshold (else the pixel would be corrected)."""
    return np.hypot(sigma_m, expected_bias_m)


def corrected_uncertainty_m(card: ModelCard, measured_sigma_m: NDArray, fused_sigma_m: NDArray,
                            correction_m: NDArray, footprint: FootprintEstimate | None,
                            inputs: NDArray | None = None) -> NDArray[np.float32]:
    """1-sigma uncertainty [m] of depths corrected by the model of ``card``.

    Parameters
    ----------
    card : The model's card (its uncertainty model, :mod:`mpi_lidar.learning.error_model`).
    measured_sigma_m : The measured depth's sd (n,). [m]
    fused_sigma_m : The fused depth's sd under the noise model (n,). [m]
    correction_m : The correction, corrected less measured depth (n,). [m]
    footprint : The scan's own footprint estimate (None: the footprint was given).
    inputs : A geometric model's inputs (n, 2) the model read, equivalent rho_ABA [1] and d_AB [m] (None: not
        known, the law alone).

    Returns
    -------
    The 1-sigma (n,) [m]: with the card's uncertainty model, the model's error as fitted on the validation rows of
    its training (68 % of their errors within it), from the fused sd and the size of the correction, scaled by the
    factor of the region of the prior the inputs lie in and, beyond the prior's reach, with the share of the
    correction the prior leaves out (:func:`~mpi_lidar.learning.error_model.corrected_sigma_m`), combined with
    the share of the correction that the footprint estimate's relative uncertainty leaves open
    (:func:`footprint_left_open`). A card without one (written before it was fitted): the measured sd and that
    share, without the model's own error.
    """
    relative = footprint_left_open(card, footprint)
    if card.uncertainty_model is None:
        base_m = np.asarray(measured_sigma_m, dtype=np.float64)
    else:
        base_m = corrected_sigma_m(card.uncertainty_model, fused_sigma_m, correction_m, inputs,
                                   None if inputs is None else card.dataset.prior.multipath_reach())
    return np.hypot(base_m, relative * np.asarray(correction_m, dtype=np.float64)).astype(np.float32)


def footprint_left_open(card: ModelCard, footprint: FootprintEstimate | None) -> float:
    """The footprint estimate's relative uncertainty [1] that a corrected depth's uncertainty must add, as a share
    of the correction (the multipath bias scales with the footprint; a given footprint, ``footprint`` None, adds
    nothing).

    A card with an uncertainty model has the validation rows' errors in it, and those rows' geometric inputs
    carried an estimation error of their coupling (``geometry_error_model``): only a footprint less certain than
    that adds the excess (in quadrature); a model without geometric inputs does not read the footprint, which then
    adds nothing. A card without an uncertainty model: the whole relative uncertainty.
    """
    if footprint is None or not np.isfinite(footprint.area_m2) or footprint.area_m2 <= 0:
        return 0.0
    relative = footprint.relative_sigma
    if card.uncertainty_model is None:
        return relative
    if not card.geometric:
        return 0.0
    trained = 0.0 if card.geometry_error_model is None else card.geometry_error_model.coupling_log_sd
    return float(np.sqrt(max(relative**2 - trained**2, 0.0)))
