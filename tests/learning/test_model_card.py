"""The typed model card: written as before, validated at load, old cards and models still load."""

from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import xgboost as xgb

from mpi_lidar.config import Config
from mpi_lidar.errors import MpiLidarError
from mpi_lidar.learning.features import GEOMETRY_ERROR_MODEL, FeatureSpec
from mpi_lidar.learning.model import CARD_FILE, MODEL_FILE, file_sha256, load_model, save_model
from mpi_lidar.learning.model_card import DatasetCard, UncertaintyCard
from mpi_lidar.learning.train import model_card, train_arrays

pytestmark = pytest.mark.unit

CONFIG = Config()
SPEC = FeatureSpec(CONFIG.frequencies_hz, "engineered", "residual")


def _rows(n: int = 2_000, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    depth = rng.uniform(1.4, 2.4, size=(n, 1))
    raw = np.hstack([depth + rng.normal(0, 0.01, (n, 4)), rng.uniform(0.01, 1.0, (n, 4))]).astype(np.float32)
    return raw, depth[:, 0]


@pytest.fixture(scope="module")
def fitted():
    raw, truth = _rows()
    return train_arrays(SPEC.transform(raw), SPEC.target(raw, truth), {"max_depth": 3}, 20, early_stopping_rounds=5)


@pytest.fixture
def model_dir(tmp_path: Path, fitted) -> Path:
    card = model_card(SPEC, DatasetCard.from_config(CONFIG, path="in memory"), {"max_depth": 3}, fitted, workers=0)
    return save_model(tmp_path / "model", fitted.booster, card)


def _old_card(model_dir: Path, geometric_key: bool = True) -> dict[str, object]:
    """A card as train wrote it before the typed card (hand-written keys, in the same layout)."""
    card = {
        "frequencies_hz": [12500000.0, 18750000.0, 25000000.0, 31250000.0],
        "raw_feature_names": SPEC.raw_names, "feature_set": "engineered", "feature_names": SPEC.names,
        "target_mode": "residual", "residual_reference": "depth_31.25MHz",
        "dataset": {"path": "/data/dataset.zarr", "config_sha256": "c2d27a81" * 8, "samples": 8000,
                    "prior": {"albedo": [0.14, 1.0], "coupling": [0.0, 1.0], "d_ab_m": [0.0, 0.15],
                              "d_as_m": [1.4, 2.4], "rho": [0.0, 1.0], "rho_aba": [0.0, 1.0], "rho_bas": [0.0, 1.0],
                              "rho_sab": [0.0, 1.0], "rho_sas": [0.0, 1.0], "scheme": "reciprocal"},
                    "simulator": {"background_mean_electrons": 0.0, "background_std_electrons": 0.0,
                                  "fidelity": "moment", "noise_scale": 1.0, "random_noise_std_v": 0.0,
                                  "round_photons": True, "tia_noise_mean_electrons": 0.0, "whole_cycles": False}},
        "params": {"colsample_bytree": 1.0, "eval_metric": "mae", "gamma": 0.0, "learning_rate": 0.3, "max_depth": 6,
                   "min_child_weight": 1.0, "objective": "reg:absoluteerror", "reg_lambda": 1.0, "subsample": 1.0,
                   "tree_method": "hist"},
        "num_boost_round": 41,
        "metrics": {"validation_mae_m": 0.00649357989265205},
        "training": {"dask_workers": 2, "fit_rows": 5756, "validation_rows": 644, "wall_s": 4.199},
        "schema": "mpi-lidar/model@1",
        "model_sha256": file_sha256(model_dir / MODEL_FILE),
        "versions": {"mpi-lidar": "0.1.0", "numpy": "2.4.6", "xgboost-cpu": "3.2.0"},
    }
    if geometric_key:
        card["geometric"] = False
    return card


def _old_model_dir(tmp_path: Path, booster: xgb.Booster, geometric_key: bool = True) -> Path:
    """A model directory as written before: a booster without feature names and a hand-written card."""
    model_dir = tmp_path / "old"
    model_dir.mkdir()
    booster.save_model(str(model_dir / MODEL_FILE))
    card = _old_card(model_dir, geometric_key)
    (model_dir / CARD_FILE).write_text(json.dumps(card, indent=2, sort_keys=True) + "\n")
    return model_dir


@pytest.mark.parametrize("geometric_key", [True, False], ids=["current", "before-geometric-inputs"])
def test_load_model__old_format_card_loads_and_predicts_as_before(tmp_path, fitted, geometric_key):
    model_dir = _old_model_dir(tmp_path, fitted.booster, geometric_key)
    model = load_model(model_dir)
    card = model.card
    assert card.geometric is False and card.geometry_error_model is None and card.uncertainty_model is None
    assert card.dataset.prior.d_as_m == (1.4, 2.4) and card.dataset.samples == 8000
    assert card.params["max_depth"] == 6 and card.training.dask_workers == 2
    assert model.booster.feature_names is None
    raw, _ = _rows(500, seed=1)
    np.testing.assert_array_equal(model.predict_depth(raw),
                                  SPEC.depth(raw, fitted.booster.inplace_predict(SPEC.transform(raw))
                                             .astype(np.float64)))
    if geometric_key:  # the typed card writes the very same file
        assert card.to_json() == (model_dir / CARD_FILE).read_text()


def test_save_model__feature_names_in_the_booster_change_no_prediction(model_dir, fitted):
    model = load_model(model_dir)
    assert model.booster.feature_names == SPEC.names == list(model.card.feature_names)
    assert fitted.booster.feature_names is None  # the caller's booster is left as it was
    raw, _ = _rows(3_000, seed=2)
    x = SPEC.transform(raw)
    np.testing.assert_array_equal(model.booster.inplace_predict(x), fitted.booster.inplace_predict(x))
    assert model.card.model_sha256 == file_sha256(model_dir / MODEL_FILE)


def test_save_model__card_round_trips_through_the_file(model_dir):
    card = load_model(model_dir).card
    assert card.to_json() == (model_dir / CARD_FILE).read_text()
    assert card.dataset.path == "in memory" and card.dataset.prior.d_as_m == CONFIG.prior.d_as_m
    assert card.training.validation_rows == 200 and card.params["max_depth"] == 3


def test_save_model__uncertainty_model_round_trips_and_is_absent_when_none(tmp_path, fitted):
    uncertainty = UncertaintyCard(noise_factor=1.03, model_sd_m=0.0021, reference_correction_m=0.01,
                                  correction_exponent=0.55, validation_rows=200, validation_coverage=0.684)
    card = model_card(SPEC, DatasetCard.from_config(CONFIG, path="in memory"), {"max_depth": 3},
                      replace(fitted, uncertainty=uncertainty), workers=0)
    model_dir = save_model(tmp_path / "model", fitted.booster, card)
    assert load_model(model_dir).card.uncertainty_model == uncertainty
    assert json.loads((model_dir / CARD_FILE).read_text())["uncertainty_model"]["model_sd_m"] == 0.0021
    assert "uncertainty_model" not in json.loads(card.model_copy(update={"uncertainty_model": None}).to_json())


def test_model_card__geometric_model_records_its_error_model():
    spec = FeatureSpec(CONFIG.frequencies_hz, "raw", "absolute", geometric=True)
    x = np.random.default_rng(3).uniform(size=(300, len(spec.names)))
    fitted = train_arrays(x, x[:, 0], {"max_depth": 2}, 3, early_stopping_rounds=None)
    card = model_card(spec, DatasetCard.from_config(CONFIG), None, fitted, workers=0)
    assert card.geometric and card.geometry_error_model.model_dump() == GEOMETRY_ERROR_MODEL
    assert "geometry_error_model" in json.loads(card.to_json())


def _rewrite(model_dir: Path, change) -> None:
    card = json.loads((model_dir / CARD_FILE).read_text())
    (model_dir / CARD_FILE).write_text(json.dumps(change(card)))


def _drop(path: str):
    def change(card: dict) -> dict:
        *parents, last = path.split(".")
        part = card
        for key in parents:
            part = part[key]
        del part[last]
        return card
    return change


def _set(path: str, value: object):
    def change(card: dict) -> dict:
        *parents, last = path.split(".")
        part = card
        for key in parents:
            part = part[key]
        part[last] = value
        return card
    return change


@pytest.mark.parametrize(("change", "expected"), [
    (_drop("feature_names"), "lacks key 'feature_names'"),
    (_drop("dataset.prior.d_as_m"), "lacks key 'dataset.prior.d_as_m'"),
    (_drop("model_sha256"), "lacks key 'model_sha256'"),
    (lambda card: [card], "holds a JSON list, not an object"),
    (_set("dataset", ["a", "b"]), "dataset: Input should be an object"),
    (_set("dataset.samples", "many"), "dataset.samples: Input should be a valid integer (found string)"),
    (_set("frequencies_hz", "31.25e6"), "frequencies_hz: Input should be a valid array"),
    (_set("dataset.prior.d_as_m", [2.4, 1.4]), "is not a (low, high) range"),
    (_set("feature_set", "fancy"), "feature_set: Input should be 'raw', 'engineered', 'range_free' or 'physical'"),
    (_set("params.max_depth", [3]), "params.max_depth: Value error, an XGBoost parameter must be"),
    (_set("metrics.validation_mae_m", None), "metrics.validation_mae_m: Input should be a valid number"),
    (_set("training.extra", 1), "has unknown key 'training.extra'"),
    (_set("schema", None), "has schema None"),
], ids=["missing-key", "missing-nested-key", "missing-hash", "list", "list-for-object", "string-for-int",
        "string-for-list", "reversed-range", "unknown-feature-set", "list-for-param", "null-for-float",
        "unknown-key", "no-schema"])
def test_load_model__malformed_card_is_one_error_line_naming_the_file(model_dir, change, expected):
    _rewrite(model_dir, change)
    with pytest.raises(MpiLidarError) as error:
        load_model(model_dir)
    message = str(error.value)
    assert str(model_dir / CARD_FILE) in message and expected in message and "\n" not in message


@pytest.mark.parametrize("text", ["{not json", "", "\xff\xfe"], ids=["broken", "empty", "not-utf8"])
def test_load_model__card_that_is_not_json_is_one_error_line(model_dir, text):
    (model_dir / CARD_FILE).write_bytes(text.encode("latin-1"))
    with pytest.raises(MpiLidarError, match=r"card\.json is not valid JSON") as error:
        load_model(model_dir)
    assert str(model_dir / CARD_FILE) in str(error.value) and "\n" not in str(error.value)


def test_load_model__feature_names_in_the_booster_must_match_the_card(model_dir):
    booster = xgb.Booster(model_file=str(model_dir / MODEL_FILE))
    booster.feature_names = [f"x{i}" for i in range(len(SPEC.names))]
    booster.save_model(str(model_dir / MODEL_FILE))
    _rewrite(model_dir, _set("model_sha256", file_sha256(model_dir / MODEL_FILE)))
    with pytest.raises(MpiLidarError, match="do not match its model"):
        load_model(model_dir)


def test_load_model__a_model_with_the_earlier_geometric_input_is_refused_with_what_to_do(model_dir):
    """Correction gives the equivalent rho_ABA now: a model that learnt the white coupling must be retrained."""
    earlier = [*SPEC.names, "geometric_coupling", "geometric_d_ab_m"]
    _rewrite(model_dir, _set("feature_names", earlier))
    with pytest.raises(MpiLidarError, match=r"earlier geometric input 'geometric_coupling'.*retrain it"):
        load_model(model_dir)


@pytest.mark.parametrize("written, reach", [
    ({"scheme": "reciprocal", "coupling": [0.0, 0.5], "albedo": [0.14, 0.8], "d_ab_m": [0.0, 0.15]}, (0.4, 0.15)),
    ({"scheme": "independent", "rho": [0.0, 0.9], "d_ab_m": [0.0, 0.3]}, (0.9, 0.3)),
    ({"scheme": "explicit", "rho_aba": [0.0, 0.7], "d_ab_m": [0.0, 0.2]}, (0.7, 0.2)),
    ({"coupling": [0.0, 1.0], "albedo": [0.14, 1.0], "d_ab_m": [0.0, 0.15]}, (1.0, 0.15)),
    ({"scheme": "reciprocal"}, None),
    ({"scheme": "explicit", "rho_aba": "high", "d_ab_m": [0.0, 0.2]}, None),
])
def test_prior_card__multipath_reach_follows_the_scheme_as_written(written, reach):
    from mpi_lidar.learning.model_card import PriorCard

    found = PriorCard.model_validate({"d_as_m": [1.4, 2.4], **written}).multipath_reach()
    assert found == (None if reach is None else pytest.approx(reach))
