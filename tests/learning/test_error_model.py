"""The corrected depths' uncertainty model: its closed form, and its calibration on held-out simulated rows."""

from __future__ import annotations

import numpy as np
import pytest

from mpi_lidar.config import Config
from mpi_lidar.learning.error_model import (
    MIN_FIT_ROWS,
    ONE_SIGMA_SHARE,
    corrected_sigma_m,
    coverage,
    error_terms,
    fit_uncertainty,
)
from mpi_lidar.learning.features import FeatureSpec, synthetic_geometry
from mpi_lidar.learning.model import booster_depth
from mpi_lidar.learning.model_card import UncertaintyCard
from mpi_lidar.learning.train import train_arrays
from mpi_lidar.physics.noise import fused_depths
from mpi_lidar.simulation.dataset import seeded_rng, simulate_rows
from mpi_lidar.simulation.sampling import THETA_NAMES

pytestmark = pytest.mark.unit

CONFIG = Config()  # the working range, 0.5-12 m
SPEC = FeatureSpec(CONFIG.frequencies_hz, "physical", "residual", geometric=True)
# Rows the booster learns from, rows the uncertainty is fitted on, rows it is checked on: three disjoint sets.
TRAIN_ROWS, FIT_ROWS, CHECK_ROWS = 10_000, 4_000, 6_000
RANGE_BANDS_M = ((0.5, 1.5), (1.5, 4.0), (4.0, 12.0))


@pytest.fixture(scope="module")
def simulated_terms() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Error terms of the fit's rows and of the check's rows (with the latter's true depths) of a small booster."""
    rows = TRAIN_ROWS + FIT_ROWS + CHECK_ROWS
    raw, theta = simulate_rows(CONFIG, rows, seeded_rng(3, 0))
    geometry = synthetic_geometry(theta, THETA_NAMES, 3, np.arange(rows))
    learn = slice(0, TRAIN_ROWS)
    booster = train_arrays(SPEC.transform(raw[learn], geometry[learn]), SPEC.target(raw[learn], theta[learn, 0]),
                           {"max_depth": 6}, 200, early_stopping_rounds=10).booster

    def terms(part: slice) -> np.ndarray:
        depth = booster_depth(booster, SPEC, raw[part], geometry[part])
        return error_terms(raw[part], depth, theta[part, 0], CONFIG.frequencies_hz, CONFIG.sensor)

    check = slice(TRAIN_ROWS + FIT_ROWS, rows)
    return terms(slice(TRAIN_ROWS, TRAIN_ROWS + FIT_ROWS)), terms(check), theta[check, 0]


@pytest.mark.unit
def test_fit_uncertainty__covers_68_percent_of_held_out_rows_in_every_range_band(simulated_terms):
    fit_terms, check_terms, true_depth = simulated_terms
    model = fit_uncertainty(fit_terms)
    assert model is not None and model.validation_rows == FIT_ROWS
    assert model.validation_coverage == pytest.approx(ONE_SIGMA_SHARE, abs=0.01), "the fit's own rows, by design"
    assert coverage(model, check_terms) == pytest.approx(ONE_SIGMA_SHARE, abs=0.04)
    for low, high in RANGE_BANDS_M:
        band = (true_depth >= low) & (true_depth < high)
        assert coverage(model, check_terms[band]) == pytest.approx(ONE_SIGMA_SHARE, abs=0.07), f"{low}-{high} m"
    assert model.noise_factor == pytest.approx(1.0, abs=0.25), "without multipath the model reaches the fused sd"
    assert 0.2 < model.correction_exponent < 1.0


@pytest.mark.unit
def test_fit_uncertainty__beats_the_noise_model_alone_on_corrected_rows(simulated_terms):
    """The fused sd alone leaves the model's own error out: far fewer rows with a large correction are covered."""
    fit_terms, check_terms, _ = simulated_terms
    model = fit_uncertainty(fit_terms)
    large = np.abs(check_terms[:, 1]) > 0.01
    noise_only = (np.abs(check_terms[large, 2]) <= check_terms[large, 0]).mean()
    assert noise_only < 0.5 and coverage(model, check_terms[large]) == pytest.approx(ONE_SIGMA_SHARE, abs=0.07)


@pytest.mark.unit
def test_fit_uncertainty__too_few_rows_fit_nothing():
    terms = np.random.default_rng(0).normal(size=(MIN_FIT_ROWS - 1, 3))
    assert fit_uncertainty(terms) is None
    terms[:, 0] = np.nan  # rows without a finite sd do not count
    assert fit_uncertainty(np.vstack([terms, terms])) is None


@pytest.mark.unit
def test_corrected_sigma_m__noise_and_model_error_in_quadrature():
    model = UncertaintyCard(noise_factor=1.0, model_sd_m=0.002, reference_correction_m=0.01, correction_exponent=0.5,
                            validation_rows=1, validation_coverage=0.68)
    sigma = corrected_sigma_m(model, np.array([0.001, 0.001, 0.003]), np.array([0.04, -0.04, 0.0]))
    # 2 mm at 10 mm grows as sqrt(|c|): 4 mm at 40 mm; no correction leaves the noise alone.
    np.testing.assert_allclose(sigma, [np.hypot(0.001, 0.004), np.hypot(0.001, 0.004), 0.003], rtol=1e-12)


@pytest.mark.unit
def test_error_terms__fused_sd_correction_and_error_of_each_row():
    raw = np.array([[2.0, 2.0, 2.0, 2.01, 0.01, 0.01, 0.01, 0.01]], dtype=np.float32)
    terms = error_terms(raw, np.array([2.003]), np.array([2.0]), CONFIG.frequencies_hz, CONFIG.sensor)
    expected_sd = fused_depths(raw, CONFIG.frequencies_hz, CONFIG.sensor).sigma_m[0]
    np.testing.assert_allclose(terms, [[expected_sd, 2.003 - float(np.float32(2.01)), 0.003]], rtol=1e-6, atol=1e-9)
