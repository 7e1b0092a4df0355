"""What takes a model or a dataset by URL besides `train --out` and `correct --model`: the Python training, the
evaluation, the tuning's storage, the sensor profile's check and the model a long-lived worker keeps (moto's S3
server on 127.0.0.1)."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from benchmarks.object_storage import OPERATIONS, install_counters, take_counters
from mpi_lidar.calibration.profile import profile_options
from mpi_lidar.config import Config
from mpi_lidar.errors import MpiLidarError
from mpi_lidar.learning.evaluate import evaluate_model
from mpi_lidar.learning.features import FeatureSpec
from mpi_lidar.learning.model import CARD_FILE, MODEL_FILE, load_model, read_card, save_model
from mpi_lidar.learning.train import train_and_save
from mpi_lidar.locations import location
from mpi_lidar.storage import objects
from mpi_lidar.workflows import correct_archive
from mpi_lidar.workflows.cluster import dask_client
from tests.cli_runner import assert_one_error_line, call_main
from tests.model_factory import tiny_model
from tests.storage.conftest import BUCKET, SECRET

pytestmark = pytest.mark.integration


@pytest.fixture(scope="module")
def model_url(s3_server, pixelwise_model) -> str:
    """The session's pixelwise model, in the bucket: its URL."""
    model = load_model(pixelwise_model)
    return str(save_model(f"s3://{BUCKET}/users/model", model.booster, model.card))


@pytest.fixture(scope="module")
def dataset_url(s3_server, small_dataset) -> str:
    """The session's small dataset (8,000 rows of the paper's prior), copied into the bucket: its URL."""
    url = f"s3://{BUCKET}/users/dataset.zarr"
    objects.filesystem(location(url)).put(str(small_dataset) + "/", location(url).path, recursive=True)
    return url


def test_train_and_save__into_bucket_publishes_whole_and_writes_nothing_here(s3_server, small_dataset, tmp_path,
                                                                             monkeypatch):
    """A URL is no local folder (``s3:/...``): the model is published there by its card, and a second training
    into it is refused before it trains. (Trained by this process's one worker thread, as ``--workers 0``.)"""
    monkeypatch.chdir(tmp_path)
    url = f"s3://{BUCKET}/users/trained"
    spec = FeatureSpec(Config().frequencies_hz, "raw", "residual")
    with dask_client(None, 0) as client:
        written, result = train_and_save(client, small_dataset, url, spec, {"max_depth": 2}, num_boost_round=3,
                                         early_stopping_rounds=2)
    assert written == url and list(tmp_path.iterdir()) == []
    assert set(objects.list_files(location(url))) == {MODEL_FILE, CARD_FILE}
    model = load_model(url)
    assert model.card.num_boost_round == result.best_iteration + 1 and model.card.dataset.path == str(small_dataset)
    assert read_card(f"{url}/{CARD_FILE}").to_json() == model.card.to_json()
    with pytest.raises(MpiLidarError, match=f"model directory {url} already exists"):
        train_and_save(None, small_dataset, url, spec)  # type: ignore[arg-type]  # refused before any cluster work


def test_evaluate__model_and_dataset_in_bucket(model_url, dataset_url, small_dataset, pixelwise_model, tmp_path,
                                               monkeypatch, capsys):
    """The metrics from the bucket are those of the same model and dataset on disk."""
    code, stdout, err = call_main(monkeypatch, capsys, "evaluate", "--data", dataset_url, "--model", model_url,
                                  "--out", tmp_path / "report")
    assert code == 0 and f"report written to {tmp_path / 'report'}" in stdout, stdout + err
    assert SECRET not in stdout + err
    written = json.loads((tmp_path / "report" / "metrics.json").read_text())
    local = evaluate_model(load_model(pixelwise_model), small_dataset).metrics
    assert written["data"] == dataset_url
    assert written["metrics"] == {name: metrics.as_dict() for name, metrics in local.items()}


def test_tune__dataset_in_bucket_needs_a_storage_url(dataset_url, monkeypatch, capsys):
    """No SQLite file beside a dataset in a bucket (the workers could not all reach one here): one line naming
    the dataset's URL whole and asking for --storage."""
    monkeypatch.delenv("MPI_LIDAR_STORAGE_URL", raising=False)
    code, stdout, err = call_main(monkeypatch, capsys, "tune", "--data", dataset_url)
    assert code == 2 and stdout == ""
    assert_one_error_line(err, f"the dataset {dataset_url} is in an object store")
    assert "--storage" in err


def test_profile_options__frequencies_checked_against_a_model_in_bucket(model_url, tmp_path):
    sensor = tmp_path / "sensor.toml"
    sensor.write_text('schema = "mpi-lidar/sensor@1"\nfootprint_area_m2 = 0.0231\n'
                      "frequencies_hz = [1e7, 1.5e7, 2e7, 3e7]\n")
    with pytest.raises(MpiLidarError, match=f"calibrated at 10, 15, 20, 30 MHz, but the model {model_url} is at"):
        profile_options(sensor, model_url)
    assert profile_options(sensor, f"s3://{BUCKET}/users/no-model") == profile_options(sensor)


def test_cached_model__bucket_model_retrained_at_same_url_is_loaded_again(model_url, pixelwise_model, tmp_path):
    """A worker keeps a model for as long as its card is the one published (one HEAD per scan), and loads the
    model published again at the same URL."""
    url = f"s3://{BUCKET}/users/retrained"
    first = load_model(pixelwise_model)
    save_model(url, first.booster, first.card)
    install_counters()
    kept = correct_archive._cached_model(url)
    take_counters()
    assert correct_archive._cached_model(url) is kept
    asked = {name: n for name, n in take_counters().items() if name in OPERATIONS}
    assert asked == {"HeadObject": 1}, asked
    objects.remove_prefix(location(url))
    second = load_model(tiny_model(tmp_path / "second", geometric=False, feature_set="raw", rows=500, rounds=3))
    save_model(url, second.booster, second.card)
    reloaded = correct_archive._cached_model(url)
    assert reloaded is not kept and reloaded.card.num_boost_round == 3 != kept.card.num_boost_round
    assert reloaded.card.model_sha256 == read_card(Path(tmp_path / "second" / CARD_FILE)).model_sha256
