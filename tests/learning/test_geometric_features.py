from __future__ import annotations

from dataclasses import replace

import dask.array as da
import numpy as np
import pytest

from mpi_lidar.config import Config, PriorConfig
from mpi_lidar.correction import NO_GEOMETRY_INPUTS_NOTE, CorrectionOptions, Flag, analyse_geometry, correct_scan
from mpi_lidar.correction.validity import usable_depth_of
from mpi_lidar.errors import MpiLidarError
from mpi_lidar.learning.evaluate import evaluate_model
from mpi_lidar.learning.features import (
    GEOMETRIC_NAMES,
    GEOMETRY_ERROR_MODEL,
    FeatureSpec,
    geometry_inputs,
    row_uniforms,
    synthetic_geometry,
    synthetic_geometry_dask,
)
from mpi_lidar.learning.model import load_model
from mpi_lidar.learning.train import train_and_save, training_geometry, training_geometry_lazy
from mpi_lidar.physics.coupling import DEFAULT_FOOTPRINT_AREA_M2
from mpi_lidar.reporting.correction_notes import correction_notes
from mpi_lidar.simulation import dataset
from mpi_lidar.simulation.sampling import THETA_NAMES, sample_theta
from mpi_lidar.simulation.scenes import corner, render
from tests.scan_factory import two_path_scan

FREQS = Config().frequencies_hz
FAST = {"max_depth": 6, "learning_rate": 0.3, "subsample": 1.0, "colsample_bytree": 1.0, "min_child_weight": 1.0,
        "reg_lambda": 1.0, "gamma": 0.0}
NO_ERROR = {"coupling_log_median": 0.0, "coupling_log_sd": 0.0, "d_ab_offset_m": 0.0, "d_ab_sd_m": 0.0}

# The footprint the scenes are rendered with: these tests are about the geometric inputs, not their calibration.
RENDER_FOOTPRINT_M2 = DEFAULT_FOOTPRINT_AREA_M2


@pytest.fixture(scope="module")
def models(tmp_path_factory, cluster_client, small_dataset):
    """The same engineered residual model with and without geometric inputs, through xgboost.dask."""
    root = tmp_path_factory.mktemp("geometric")
    out = {}
    for geometric in (False, True):
        spec = FeatureSpec(FREQS, "engineered", "residual", geometric)
        out[geometric], _ = train_and_save(cluster_client, small_dataset, root / f"geometric_{geometric}", spec,
                                           FAST, num_boost_round=100, early_stopping_rounds=10)
    return out


@pytest.mark.unit
def test_synthetic_geometry__error_statistics_match_the_error_model():
    prior = PriorConfig()
    theta = sample_theta(prior, 100_000, np.random.default_rng(3))
    theta[:10_000, THETA_NAMES.index("rho_aba")] = 0.0
    estimate = synthetic_geometry(theta, THETA_NAMES, seed=5, rows=np.arange(theta.shape[0]))
    np.testing.assert_array_equal(estimate[:10_000], 0.0)
    rho_aba, d_ab = theta[10_000:, 4], theta[10_000:, 1]
    log_ratio = np.log(estimate[10_000:, 0] / rho_aba)
    assert np.median(log_ratio) == pytest.approx(GEOMETRY_ERROR_MODEL["coupling_log_median"], abs=0.01)
    assert np.std(log_ratio) == pytest.approx(GEOMETRY_ERROR_MODEL["coupling_log_sd"], rel=0.02)
    far = d_ab > 0.08  # well clear of the clip at 0
    error = estimate[10_000:, 1][far] - d_ab[far]
    assert error.mean() == pytest.approx(GEOMETRY_ERROR_MODEL["d_ab_offset_m"], abs=3e-4)
    assert error.std() == pytest.approx(GEOMETRY_ERROR_MODEL["d_ab_sd_m"], rel=0.02)
    assert (estimate[:, 1] >= 0).all()


@pytest.mark.unit
def test_synthetic_geometry__without_error_a_training_row_gets_its_own_rho_aba_and_d_ab():
    theta = sample_theta(PriorConfig(), 2_000, np.random.default_rng(8))
    exact = synthetic_geometry(theta, THETA_NAMES, seed=2, rows=np.arange(2_000), error_model=NO_ERROR)
    np.testing.assert_allclose(exact, theta[:, [4, 1]], rtol=1e-12)


@pytest.mark.unit
def test_row_uniforms__a_row_gets_the_same_values_in_any_subset_or_chunking():
    full = row_uniforms(7, np.arange(5_000))
    rows = np.sort(np.random.default_rng(0).choice(5_000, 300, replace=False))
    np.testing.assert_array_equal(row_uniforms(7, rows), full[rows])
    assert not np.array_equal(row_uniforms(8, rows), full[rows])
    theta = sample_theta(PriorConfig(), 5_000, np.random.default_rng(1))
    lazy = synthetic_geometry_dask(da.from_array(theta, chunks=(777, 3)), THETA_NAMES, 7).compute()
    np.testing.assert_array_equal(lazy, synthetic_geometry(theta, THETA_NAMES, 7, np.arange(5_000)))
    assert full.min() > 0 and full.max() < 1
    assert np.abs(full.mean(0) - 0.5).max() < 0.01


@pytest.mark.integration
def test_training_geometry__train_tune_and_evaluate_rows_agree(small_dataset):
    spec = FeatureSpec(FREQS, "engineered", "residual", geometric=True)
    lazy = training_geometry_lazy(spec, dataset.read_lazy(small_dataset)).compute()
    sub = dataset.read_subsample(small_dataset, split="test")
    np.testing.assert_array_equal(training_geometry(spec, sub), lazy[sub.rows])
    tuning = dataset.read_subsample(small_dataset, split="train", max_rows=500, seed=3)
    np.testing.assert_array_equal(training_geometry(spec, tuning), lazy[tuning.rows])
    assert training_geometry(FeatureSpec(FREQS, "engineered", "residual"), sub) is None


@pytest.mark.unit
def test_feature_spec__geometric_inputs_are_required_and_appended():
    spec = FeatureSpec(FREQS, "engineered", "residual", geometric=True)
    raw = two_path_scan("g").raw_pixels()
    assert spec.names[-2:] == list(GEOMETRIC_NAMES)
    with pytest.raises(MpiLidarError, match="trained with geometric features"):
        spec.transform(raw)
    geometry = np.column_stack([np.full(raw.shape[0], 0.3), np.full(raw.shape[0], 0.05)])
    x = spec.transform(raw, geometry)
    assert x.shape == (raw.shape[0], len(spec.names))
    np.testing.assert_allclose(x[:, -2:], geometry, rtol=1e-6)
    lazy = spec.transform(da.from_array(raw, chunks=(100, 8)), da.from_array(geometry, chunks=(64, 2))).compute()
    np.testing.assert_array_equal(lazy, x)


@pytest.mark.unit
def test_geometry_inputs__no_partner_gives_zeros():
    out = geometry_inputs(np.array([0.0, 0.2, np.nan]), np.array([np.nan, 0.04, np.nan]))
    np.testing.assert_array_equal(out, [[0.0, 0.0], [0.2, 0.04], [0.0, 0.0]])


@pytest.mark.integration
@pytest.mark.slow
def test_train_and_save__card_records_the_geometric_option(models):
    card = load_model(models[True]).card
    assert card.geometric is True and card.feature_names[-2:] == GEOMETRIC_NAMES
    assert card.geometry_error_model.model_dump() == GEOMETRY_ERROR_MODEL
    pixelwise = load_model(models[False]).card
    assert pixelwise.geometric is False and pixelwise.geometry_error_model is None


@pytest.mark.integration
@pytest.mark.slow
def test_predict_depth__geometric_model_refuses_rows_without_inputs(models):
    model = load_model(models[True])
    with pytest.raises(MpiLidarError, match="needs them for every pixel"):
        model.predict_depth(two_path_scan("r").raw_pixels())


@pytest.mark.integration
@pytest.mark.slow
def test_evaluate_model__geometric_inputs_beat_pixel_wise_on_varying_coupling(models, small_dataset):
    geometric = evaluate_model(load_model(models[True]), small_dataset).metrics["corrected (XGBoost)"].mae_m
    pixel_wise = evaluate_model(load_model(models[False]), small_dataset).metrics["corrected (XGBoost)"].mae_m
    assert geometric < 0.85 * pixel_wise


@pytest.mark.integration
@pytest.mark.slow
def test_correct_scan__geometric_model_gets_the_gate_estimates(models):
    scan = render(corner(90.0, 2.0, 0.8, height=40, width=96), Config(), np.random.default_rng(2))
    model = load_model(models[True])
    options = CorrectionOptions(footprint_area_m2=RENDER_FOOTPRINT_M2)
    correction = correct_scan(scan, model, options)
    corrected = correction.flags.ravel() == Flag.CORRECTED
    assert corrected.sum() > 100
    raw = scan.raw_pixels()
    # What the scene geometry read: the usable pixels' depth and the scan's own noise law (its planes rest on both).
    scene = analyse_geometry(scan, usable_depth_of(raw, correction.flags.ravel()), options, Config().sensor,
                             with_model_inputs=True, noise=correction.reading.noise)
    inputs = geometry_inputs(*scene.model_inputs.pixels(np.flatnonzero(corrected), raw[corrected, len(FREQS) - 1]))
    assert (inputs[:, 0] > 0).all()
    np.testing.assert_allclose(correction.depth.ravel()[corrected], model.predict_depth(raw[corrected], inputs),
                               atol=1e-6)
    with_gate_all = correct_scan(scan, model, CorrectionOptions(gate="all", footprint_area_m2=RENDER_FOOTPRINT_M2))
    assert with_gate_all.model_pixels() > correction.model_pixels()


def _corrected_errors(models, scan) -> tuple[dict[bool, float], float]:
    """MAE [m] of each model's correction (pixel-wise: False, geometric: True) and of the raw depth over the
    pixels the geometric model corrected."""
    errors = {}
    for geometric, path in models.items():
        correction = correct_scan(scan, load_model(path), CorrectionOptions(footprint_area_m2=RENDER_FOOTPRINT_M2))
        corrected = correction.flags == Flag.CORRECTED
        errors[geometric] = np.abs(correction.depth - scan.reference_depth)[corrected].mean()
    return errors, np.abs(scan.depth[-1] - scan.reference_depth)[corrected].mean()


@pytest.mark.integration
@pytest.mark.slow
def test_correct_scan__geometric_model_beats_pixel_wise_where_multipath_is_far_from_the_prior_average(models):
    """A 60-degree corner holds about twice the multipath the prior averages: a pixel-wise model takes off the
    average, a geometric one what the geometry says is there."""
    errors, raw = _corrected_errors(models, render(corner(60.0, 2.0, 0.8, height=40, width=96), Config(),
                                                   np.random.default_rng(4)))
    assert errors[True] < 0.6 * errors[False]
    assert errors[False] < 0.8 * raw


@pytest.mark.integration
@pytest.mark.slow
def test_correct_scan__geometric_model_matches_pixel_wise_where_multipath_is_near_the_prior_average(models):
    """On a right-angled corner 2 m away the multipath lies near the prior's average, so the pixel-wise model's
    guess is good there too: the geometric model does as well (within 10 %) and both halve the raw error."""
    errors, raw = _corrected_errors(models, render(corner(90.0, 2.0, 0.8, height=40, width=96), Config(),
                                                   np.random.default_rng(4)))
    assert errors[True] < 1.1 * errors[False]
    assert max(errors.values()) < 0.5 * raw


@pytest.mark.integration
@pytest.mark.slow
def test_correct_scan__geometric_model_keeps_raw_depth_without_scan_geometry(models):
    scan = replace(two_path_scan("n"), azimuth_rad=None, elevation_rad=None, ray_directions=None)
    correction = correct_scan(scan, load_model(models[True]), CorrectionOptions(baseline="raw"))
    assert NO_GEOMETRY_INPUTS_NOTE in correction_notes(correction)
    assert correction.counts()["corrected"] == 0
    assert correction.unserved is not None and correction.unserved.reason == "no_geometry"
    assert "mpi-lidar import-scan" in correction.unserved.message
    np.testing.assert_array_equal(correction.depth.ravel(), scan.raw_pixels()[:, len(FREQS) - 1].astype(np.float32))
