"""The corrected depths' uncertainty per region of the prior: closed forms on synthetic heteroscedastic errors."""

from __future__ import annotations

import json

import numpy as np
import pytest

from mpi_lidar.learning.error_model import (
    MIN_REGION_ROWS,
    ONE_SIGMA_SHARE,
    beyond_prior,
    beyond_prior_share,
    corrected_sigma_m,
    coverage,
    fit_region_scales,
    fit_uncertainty,
    region_factor,
)
from mpi_lidar.learning.model_card import RegionScales, UncertaintyCard

# The error's sd by region: weak multipath 1 mm, strong (rho_ABA >= 1) 4 mm, and 2 mm where d_AB >= 0.25 m.
ROWS = 6_000


def _true_sd_m(inputs: np.ndarray) -> np.ndarray:
    sd = np.full(inputs.shape[0], 0.001)
    sd[inputs[:, 1] >= 0.25] = 0.002
    sd[inputs[:, 0] >= 1.0] = 0.004
    return sd


def _terms(seed: int) -> np.ndarray:
    """Rows (n, 5) of error terms: fused sd 1 mm, correction 10 mm, errors N(0, sd^2) of their region, inputs."""
    rng = np.random.default_rng(seed)
    # One input value inside each of the 5 x 3 regions, so that every region holds about 400 rows.
    inputs = np.column_stack([rng.choice([0.02, 0.1, 0.3, 0.7, 1.5], ROWS), rng.choice([0.05, 0.15, 0.4], ROWS)])
    error = rng.standard_normal(ROWS) * _true_sd_m(inputs)
    return np.column_stack([np.full(ROWS, 0.001), np.full(ROWS, 0.01), error, inputs])


@pytest.mark.unit
def test_fit_uncertainty__region_sigma_is_each_region_s_true_sd():
    card = fit_uncertainty(_terms(0))
    assert card is not None and card.region_scales is not None
    check = _terms(1)
    sigma = corrected_sigma_m(card, check[:, 0], check[:, 1], check[:, 3:5])
    # The 68.27 % quantile of |N(0, sd^2)| is sd itself: each region's sigma must land on its sd.
    # A region of 400 rows knows its quantile to about 4 % (sd about 0.75 / sqrt(rows) of it): 3.5 sd.
    np.testing.assert_allclose(sigma, _true_sd_m(check[:, 3:5]), rtol=0.15)
    for strong in (False, True):
        rows = check[(check[:, 3] >= 1.0) == strong]
        assert coverage(card, rows) == pytest.approx(ONE_SIGMA_SHARE, abs=0.025), f"strong {strong}"


@pytest.mark.unit
def test_fit_uncertainty__the_law_alone_misses_the_strong_region_as_a_gaussian_says():
    card = fit_uncertainty(_terms(0)[:, :3])  # no inputs: one sigma for all rows
    assert card is not None and card.region_scales is None
    check = _terms(1)
    strong = check[check[:, 3] >= 1.0]
    sigma = float(corrected_sigma_m(card, strong[:1, 0], strong[:1, 1])[0])
    from scipy.special import erf

    expected = erf(sigma / (0.004 * np.sqrt(2)))  # P(|N(0, 4 mm)| <= sigma)
    assert coverage(card, strong[:, :3]) == pytest.approx(expected, abs=0.03)
    assert expected < 0.55, "the global sigma covers the strong corners far too little"


@pytest.mark.unit
def test_fit_region_scales__sparse_bins_take_their_row_s_factor():
    inputs = np.array([[0.01, 0.05]] * 100 + [[0.01, 0.3]] * (MIN_REGION_ROWS - 1))
    ratio = np.concatenate([np.full(100, 2.0), np.full(MIN_REGION_ROWS - 1, 9.0)])
    scales = fit_region_scales(ratio, inputs, (0.0, 1.0), (0.0, 0.25))
    assert scales.factors[0][0] == pytest.approx(2.0)
    assert scales.factors[0][1] == pytest.approx(np.quantile(ratio, ONE_SIGMA_SHARE)), "too few: the row's"
    assert scales.factors[1] == (1.0, 1.0), "an empty row: the law alone"
    np.testing.assert_allclose(region_factor(scales, np.array([[5.0, 9.0], [np.nan, np.nan]])), [1.0, 2.0])


@pytest.mark.unit
def test_beyond_prior_share__the_strength_past_the_prior_s_reach():
    reach = (2.0, 0.6)
    inputs = np.array([[1.0, 0.3], [4.0, 0.3], [4.0, 1.2], [0.0, 0.0], [2.0, 0.9]])
    np.testing.assert_array_equal(beyond_prior(inputs, reach), [False, True, True, False, True])
    np.testing.assert_allclose(beyond_prior_share(inputs, reach), [0.0, 1.0, 3.0, 0.0, 0.5])
    card = UncertaintyCard(noise_factor=1.0, model_sd_m=0.002, reference_correction_m=0.01, correction_exponent=0.0,
                           validation_rows=1_000, validation_coverage=0.68)
    sigma = corrected_sigma_m(card, np.zeros(5), np.full(5, 0.01), inputs, reach)
    np.testing.assert_allclose(sigma, np.hypot(0.002, 0.01 * np.array([0.0, 1.0, 3.0, 0.0, 0.5])))


@pytest.mark.unit
def test_uncertainty_card__old_cards_read_and_region_scales_round_trip():
    old = {"noise_factor": 1.1, "model_sd_m": 0.002, "reference_correction_m": 0.01, "correction_exponent": 0.7,
           "validation_rows": 1610, "validation_coverage": 0.68}
    assert UncertaintyCard.model_validate_json(json.dumps(old), strict=True).region_scales is None
    scales = RegionScales(rho_aba_edges=(0.0, 1.0), d_ab_edges_m=(0.0,), factors=((0.9,), (2.5,)))
    card = UncertaintyCard(**old, region_scales=scales)
    assert UncertaintyCard.model_validate_json(card.model_dump_json(), strict=True) == card
    with pytest.raises(ValueError, match="one per region"):
        RegionScales(rho_aba_edges=(0.0, 1.0), d_ab_edges_m=(0.0,), factors=((0.9,),))
