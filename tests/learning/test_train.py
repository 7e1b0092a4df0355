from __future__ import annotations

import json
import shutil

import numpy as np
import pytest

from mpi_lidar.config import Config, PriorConfig
from mpi_lidar.errors import MpiLidarError
from mpi_lidar.learning.evaluate import evaluate_model
from mpi_lidar.learning.features import FeatureSpec
from mpi_lidar.learning.model import load_model, save_model
from mpi_lidar.learning.train import BASE_PARAMS, DEFAULT_PARAMS, train_and_save, train_arrays, xgb_params
from mpi_lidar.reporting.report import evaluation_report, write_report
from mpi_lidar.simulation import dataset
from mpi_lidar.workflows.generate import generate

FREQS = Config().frequencies_hz
FAST = {"max_depth": 6, "learning_rate": 0.3, "subsample": 1.0, "colsample_bytree": 1.0, "min_child_weight": 1.0,
        "reg_lambda": 1.0, "gamma": 0.0}


@pytest.fixture(scope="module")
def trained(tmp_path_factory, cluster_client, small_dataset):
    """One model per target mode, trained through xgboost.dask on the shared cluster."""
    root = tmp_path_factory.mktemp("models")
    models = {}
    for target in ("absolute", "residual"):
        out, _ = train_and_save(cluster_client, small_dataset, root / target, FeatureSpec(FREQS, "raw", target),
                                FAST, num_boost_round=200, early_stopping_rounds=10)
        models[target] = out
    return models


@pytest.mark.integration
def test_train_and_save__card_describes_model_and_data(trained, small_dataset):
    model = load_model(trained["residual"])
    card = model.card
    info = dataset.dataset_info(small_dataset)
    assert card.frequencies_hz == FREQS
    assert card.raw_feature_names == info.feature_names
    assert card.target_mode == "residual" and card.residual_reference == "depth_31.25MHz"
    assert card.dataset.config_sha256 == info.config_sha256 and card.dataset.samples == 8_000
    assert card.dataset.prior.d_as_m == PriorConfig().d_as_m  # the small dataset's: the paper's prior
    assert card.params == {**BASE_PARAMS, **FAST}
    assert 0 < card.metrics.validation_mae_m < 0.02
    assert card.training.fit_rows + card.training.validation_rows == 6_400
    assert card.num_boost_round == model.booster.num_boosted_rounds()
    assert {"xgboost-cpu", "numpy", "mpi-lidar"} <= set(card.versions)
    assert model.booster.feature_names == list(card.feature_names)  # stored in the booster too
    assert (trained["residual"] / "model.ubj").read_bytes()[:1] == b"{"  # UBJSON, not a pickle
    # the file keeps the keys cards have always had, and the uncertainty model fitted on the validation rows
    assert set(json.loads((trained["residual"] / "card.json").read_text())) == {
        "schema", "frequencies_hz", "raw_feature_names", "feature_set", "feature_names", "geometric", "target_mode",
        "residual_reference", "dataset", "params", "num_boost_round", "metrics", "training", "versions",
        "model_sha256", "uncertainty_model"}
    uncertainty = card.uncertainty_model
    assert uncertainty is not None and uncertainty.validation_rows == card.training.validation_rows
    assert uncertainty.validation_coverage == pytest.approx(0.6827, abs=0.02)


@pytest.mark.integration
@pytest.mark.parametrize("target", ["absolute", "residual"])
def test_evaluate_model__correction_beats_raw_depth_on_test_split(trained, small_dataset, target):
    evaluation = evaluate_model(load_model(trained[target]), small_dataset)
    raw, corrected = evaluation.metrics["raw depth 31.25MHz"], evaluation.metrics["corrected (XGBoost)"]
    assert corrected.rows == raw.rows == 1_600
    assert corrected.mae_m < 0.85 * raw.mae_m
    # xgboost.dask is not bit-reproducible (the scheduler places the chunks and each worker sketches its own
    # quantiles): over runs on 2026-11-24 the models kept 10-30 % of the raw bias. The claim is "most of it".
    assert abs(corrected.bias_m) < 0.5 * abs(raw.bias_m)


@pytest.mark.integration
def test_predict_depth__inplace_and_dask_agree(trained, small_dataset, cluster_client):
    model = load_model(trained["residual"])
    lazy = dataset.read_lazy(small_dataset)
    in_process = model.predict_depth(lazy.features[:3000].compute())
    on_cluster = model.predict_depth_dask(cluster_client, lazy.features[:3000]).compute()
    np.testing.assert_allclose(on_cluster, in_process, rtol=0, atol=1e-6)


@pytest.mark.integration
def test_predict_depth__residual_is_added_to_the_reference_depth(trained, small_dataset):
    model = load_model(trained["residual"])
    sub = dataset.read_subsample(small_dataset, split="test", max_rows=50)
    residual = model.booster.inplace_predict(sub.features)
    np.testing.assert_allclose(model.predict_depth(sub.features), sub.features[:, 3] + residual, atol=1e-6)


@pytest.mark.integration
def test_feature_spec__engineered_transform_is_the_same_on_numpy_and_dask(small_dataset):
    spec = FeatureSpec(FREQS, "engineered", "residual")
    lazy = dataset.read_lazy(small_dataset)
    eager = spec.transform(lazy.features.compute())
    assert eager.shape == (8_000, len(spec.names)) == (8_000, 16)
    np.testing.assert_array_equal(spec.transform(lazy.features).compute(), eager)
    np.testing.assert_allclose(eager[:, 8], eager[:, 0] - eager[:, 3], atol=1e-6)


@pytest.mark.integration
def test_save_model__existing_directory_is_not_overwritten(trained):
    model = load_model(trained["absolute"])
    before = (trained["absolute"] / "card.json").read_text()
    with pytest.raises(MpiLidarError, match="already exists"):
        save_model(trained["absolute"], model.booster, model.card)
    assert (trained["absolute"] / "card.json").read_text() == before


@pytest.mark.integration
def test_load_model__tampered_model_file_is_refused(trained, tmp_path):
    copy = tmp_path / "copy"
    shutil.copytree(trained["absolute"], copy)
    (copy / "model.ubj").write_bytes((copy / "model.ubj").read_bytes()[:-10])
    with pytest.raises(MpiLidarError, match="does not match the hash"):
        load_model(copy)


@pytest.mark.integration
def test_load_model__card_features_that_do_not_match_the_model_are_refused(trained, tmp_path):
    copy = tmp_path / "copy"
    shutil.copytree(trained["absolute"], copy)
    card = json.loads((copy / "card.json").read_text())
    card["feature_set"] = "engineered"
    (copy / "card.json").write_text(json.dumps(card))
    with pytest.raises(MpiLidarError, match="do not match"):
        load_model(copy)


@pytest.mark.unit
def test_load_model__directory_without_card_is_refused(tmp_path):
    (tmp_path / "model.ubj").write_bytes(b"{}")
    with pytest.raises(MpiLidarError, match="not a model directory"):
        load_model(tmp_path)


@pytest.mark.integration
def test_check_compatible__other_frequencies_are_refused_in_one_line(trained):
    model = load_model(trained["absolute"])
    three = (12.5e6, 25e6, 31.25e6)
    with pytest.raises(MpiLidarError, match=r"12\.5, 25, 31\.25 MHz but the model expects") as error:
        model.check_compatible(three, FeatureSpec(three).raw_names, "scan x")
    assert "\n" not in str(error.value)


@pytest.mark.integration
def test_train_and_save__dataset_without_train_rows_is_refused(tmp_path, cluster_client):
    path = tmp_path / "all_test.zarr"
    generate(path, Config().replace(dataset={"samples": 1, "chunk_rows": 1, "test_fraction": 0.6}))
    with pytest.raises(MpiLidarError, match="no train rows"):
        train_and_save(cluster_client, path, tmp_path / "m", FeatureSpec(FREQS), FAST)
    assert not (tmp_path / "m").exists()


@pytest.mark.integration
def test_write_report__files_written_and_foreign_directory_refused(trained, small_dataset, tmp_path):
    model = load_model(trained["absolute"])
    report, figures = evaluation_report(evaluate_model(model, small_dataset), model.card)
    out = write_report(report, tmp_path / "report", figures)
    assert {p.name for p in out.iterdir()} >= {"report.md", "report.html", "metrics.json", "error_hist.png"}
    assert (out / "error_hist.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    metrics = json.loads((out / "metrics.json").read_text())["metrics"]
    assert metrics["corrected (XGBoost)"]["mae_m"] < metrics["raw depth 31.25MHz"]["mae_m"]
    foreign = tmp_path / "mine"
    foreign.mkdir()
    (foreign / "notes.txt").write_text("keep")
    report, figures = evaluation_report(evaluate_model(model, small_dataset), model.card)
    with pytest.raises(MpiLidarError, match="not an mpi-lidar report"):
        write_report(report, foreign, figures)
    assert (foreign / "notes.txt").read_text() == "keep"


@pytest.mark.unit
def test_train_arrays__early_stopping_trims_to_the_best_iteration():
    x = np.random.default_rng(0).uniform(size=(2_000, 2))
    y = x[:, 0] * 2.0
    result = train_arrays(x, y, {"max_depth": 3, "learning_rate": 0.3}, 500, early_stopping_rounds=5)
    assert result.booster.num_boosted_rounds() == result.best_iteration + 1 < 500
    assert result.fit_rows == 1_800 and result.validation_rows == 200 and result.wall_s > 0
    assert 0 < result.validation_mae_m < 0.02
    assert np.abs(result.booster.inplace_predict(x) - y).mean() < 0.02


@pytest.mark.unit
def test_train_arrays__without_early_stopping_fits_every_row_for_every_round():
    x = np.random.default_rng(1).uniform(size=(500, 3))
    result = train_arrays(x, x.sum(axis=1), {"max_depth": 2}, 7, early_stopping_rounds=None)
    assert result.booster.num_boosted_rounds() == 7 and result.best_iteration == 6
    assert result.fit_rows == 500 and result.validation_rows == 0 and np.isnan(result.validation_mae_m)


@pytest.mark.unit
def test_xgb_params__base_then_params_or_defaults_then_overrides():
    assert xgb_params() == {**BASE_PARAMS, **DEFAULT_PARAMS}
    assert xgb_params({"max_depth": 3}, nthread=1) == {**BASE_PARAMS, "max_depth": 3, "nthread": 1}
    assert xgb_params({"objective": "reg:squarederror"})["objective"] == "reg:squarederror"
