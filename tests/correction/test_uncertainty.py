"""The corrected depths' uncertainty: the card's uncertainty model, the footprint's share, old cards as before."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from mpi_lidar.config import Config
from mpi_lidar.correction import CorrectionOptions, correct_scan
from mpi_lidar.correction.footprint import FootprintEstimate
from mpi_lidar.correction.options import Estimate, Flag
from mpi_lidar.correction.uncertainty import corrected_uncertainty_m, footprint_left_open
from mpi_lidar.learning.error_model import corrected_sigma_m
from mpi_lidar.learning.model import load_model
from mpi_lidar.learning.model_card import UncertaintyCard
from mpi_lidar.simulation.scenes import corner, render
from tests.model_factory import tiny_model

UNCERTAINTY = UncertaintyCard(noise_factor=1.0, model_sd_m=0.002, reference_correction_m=0.01,
                              correction_exponent=0.5, validation_rows=1_000, validation_coverage=0.68)


@pytest.fixture(scope="module")
def geometric_model(tmp_path_factory):
    """A tiny geometric model as trained without an uncertainty model (an old card's behaviour)."""
    model = load_model(tiny_model(tmp_path_factory.mktemp("uncertainty") / "model", geometric=True))
    assert model.card.uncertainty_model is None
    return model


def _with_uncertainty(model, geometric: bool = True):
    return replace(model, card=model.card.model_copy(update={"uncertainty_model": UNCERTAINTY,
                                                             "geometric": geometric}))


def _footprint(relative: float) -> FootprintEstimate:
    return FootprintEstimate(area_m2=0.05, sigma_m2=relative * 0.05, pixels=1_000, surfaces=2)


@pytest.mark.unit
def test_footprint_left_open__only_what_the_trained_geometric_inputs_did_not_hold(geometric_model):
    card = geometric_model.card
    trained = card.geometry_error_model.coupling_log_sd  # 0.2
    fitted = _with_uncertainty(geometric_model).card
    assert footprint_left_open(card, _footprint(0.25)) == pytest.approx(0.25), "an old card: the whole share"
    assert footprint_left_open(fitted, _footprint(0.25)) == pytest.approx(np.sqrt(0.25**2 - trained**2))
    assert footprint_left_open(fitted, _footprint(0.1)) == 0.0, "within the training's own estimation error"
    assert footprint_left_open(_with_uncertainty(geometric_model, geometric=False).card, _footprint(0.5)) == 0.0
    assert footprint_left_open(fitted, None) == 0.0, "a given footprint"
    assert footprint_left_open(card, FootprintEstimate(float("nan"), float("inf"), 0, 0)) == 0.0
    # A sure estimate whose depth and amplitude read 1.5x apart (a path-traced strong corner): half of log 1.5
    # joins its 10 % and passes the training's 20 %.
    apart = replace(_footprint(0.1), depth_m2=0.04, amplitude_m2=0.06)
    assert footprint_left_open(fitted, apart) == pytest.approx(np.sqrt(0.1**2 + np.log(1.5)**2 / 4 - trained**2))


@pytest.mark.unit
def test_corrected_uncertainty_m__old_card_keeps_the_measured_sd_and_the_footprints_share(geometric_model):
    measured, fused, correction = np.array([0.001, 0.002]), np.array([0.0007, 0.0014]), np.array([0.02, -0.01])
    old = corrected_uncertainty_m(geometric_model.card, measured, fused, correction, _footprint(0.1))
    np.testing.assert_allclose(old, np.hypot(measured, 0.1 * correction), rtol=1e-6)
    new = corrected_uncertainty_m(_with_uncertainty(geometric_model).card, measured, fused, correction,
                                  _footprint(0.25))
    left_open = np.sqrt(0.25**2 - 0.2**2)
    np.testing.assert_allclose(new, np.hypot(corrected_sigma_m(UNCERTAINTY, fused, correction),
                                             left_open * correction), rtol=1e-6)


@pytest.mark.unit
def test_correct_scan__corrected_pixels_take_the_cards_uncertainty_model(geometric_model):
    scan = render(corner(90.0, 2.0, 0.8, height=24, width=48), Config(), np.random.default_rng(3))
    options = CorrectionOptions(footprint_area_m2=0.05)  # a given footprint: no share of its own
    correction = correct_scan(scan, _with_uncertainty(geometric_model), options)
    # Within the prior the law alone (the card has no region factors); beyond it the test of test_beyond_prior.py.
    corrected = correction.flags == Flag.CORRECTED
    assert corrected.sum() > 50
    raw = scan.raw_pixels()[corrected.ravel()]
    assert correction.reading is not None
    fused_sigma = correction.reading.noise.fuse(raw).sigma_m  # the scan's own noise law
    expected = corrected_sigma_m(UNCERTAINTY, fused_sigma, (correction.depth - correction.measured_depth)[corrected])
    np.testing.assert_allclose(correction.uncertainty_m[corrected], expected, rtol=1e-5)
    old = correct_scan(scan, geometric_model, options)
    np.testing.assert_array_equal(old.depth, correction.depth)
    others = correction.estimate != Estimate.CORRECTED
    np.testing.assert_array_equal(old.uncertainty_m[others], correction.uncertainty_m[others])
