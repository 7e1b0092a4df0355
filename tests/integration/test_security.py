"""Credentials never show; models load only from XGBoost's format with their card.

The password test of a whole tuning and training run is in test_cluster_pipeline.py.
"""

from __future__ import annotations

import json
import pickle
import shutil
from pathlib import Path

import pytest

from mpi_lidar.errors import MpiLidarError
from mpi_lidar.learning import model as model_io
from mpi_lidar.learning import tune
from tests.integration.conftest import free_port, run_cli, subprocess_env

PASSWORD = "Tr1cky-s3cret-pw"


@pytest.mark.slow
def test_cli_tune__unreachable_storage_error_line_masks_password(tmp_path: Path, small_dataset: Path) -> None:
    url = f"postgresql://analyst:{PASSWORD}@127.0.0.1:{free_port()}/studies"
    result = run_cli("tune", "--data", str(small_dataset), "--trials", "1", "--workers", "1",
                     env=subprocess_env(MPI_LIDAR_STORAGE_URL=url), check=False)
    lines = result.stderr.strip().splitlines()
    assert result.returncode == 2 and len(lines) == 1 and lines[0].startswith("error: cannot reach Optuna storage")
    assert "analyst:***@127.0.0.1" in lines[0] and PASSWORD not in result.stdout + result.stderr


def test_storage_url__argument_then_environment_then_sqlite_beside_the_data(
    monkeypatch: pytest.MonkeyPatch, tmp_path: Path
) -> None:
    monkeypatch.delenv(tune.STORAGE_URL_VARIABLE, raising=False)
    assert tune.storage_url(None, tmp_path / "d.zarr") == f"sqlite:///{tmp_path / 'optuna.db'}"
    monkeypatch.setenv(tune.STORAGE_URL_VARIABLE, "postgresql://u@db/x")
    assert tune.storage_url(None, tmp_path / "d.zarr") == "postgresql://u@db/x"
    assert tune.storage_url("sqlite:///y.db", tmp_path / "d.zarr") == "sqlite:///y.db"


def test_masked__hides_password_of_every_url_form() -> None:
    for url in (f"postgresql://u:{PASSWORD}@h:5432/db", f"postgresql+psycopg://u:{PASSWORD}@h/db",
                f"mysql://u:{PASSWORD}@h/db?ssl=true"):
        assert PASSWORD not in tune.masked(url) and "***" in tune.masked(url)
    assert PASSWORD not in tune.masked(f"not a url {PASSWORD}")


@pytest.fixture
def model_copy(tmp_path: Path, cluster_model: Path) -> Path:
    return Path(shutil.copytree(cluster_model, tmp_path / "model"))


@pytest.mark.slow
def test_load_model__pickle_named_model_ubj_is_refused(model_copy: Path) -> None:
    booster = model_io.load_model(model_copy).booster
    (model_copy / model_io.MODEL_FILE).write_bytes(pickle.dumps(booster))
    with pytest.raises(MpiLidarError, match="does not match the hash in its card"):
        model_io.load_model(model_copy)
    card = json.loads((model_copy / model_io.CARD_FILE).read_text())
    card["model_sha256"] = model_io.file_sha256(model_copy / model_io.MODEL_FILE)  # a forged card
    (model_copy / model_io.CARD_FILE).write_text(json.dumps(card))
    with pytest.raises(MpiLidarError, match="not a readable XGBoost model"):
        model_io.load_model(model_copy)


@pytest.mark.slow
@pytest.mark.parametrize("change", ["schema", "features", "frequencies"])
def test_load_model__tampered_card_is_refused(model_copy: Path, change: str) -> None:
    card = json.loads((model_copy / model_io.CARD_FILE).read_text())
    if change == "schema":
        card["schema"] = "pickle@1"
    elif change == "features":
        card["feature_names"] = card["feature_names"][:-1]
    else:
        card["frequencies_hz"] = card["frequencies_hz"][:-1]
    (model_copy / model_io.CARD_FILE).write_text(json.dumps(card))
    with pytest.raises(MpiLidarError):
        model = model_io.load_model(model_copy)
        model.check_compatible((12.5e6, 18.75e6, 25e6, 31.25e6), model.spec.raw_names, "scan x")
