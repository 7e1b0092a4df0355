"""Models in a bucket: trained into one, published whole by their card, loaded and corrected with from there
(moto's S3 server on 127.0.0.1)."""

from __future__ import annotations

import hashlib
import json
import pickle

import numpy as np
import pytest
import zarr

import mpi_lidar
from benchmarks.object_storage import OPERATIONS, install_counters, take_counters
from mpi_lidar.errors import MpiLidarError
from mpi_lidar.learning.model import CARD_FILE, MODEL_FILE, load_model, read_card, save_model, staged_model
from mpi_lidar.locations import location
from mpi_lidar.scans.store import write_scan
from mpi_lidar.storage import objects
from tests.cli_runner import call_main
from tests.scan_factory import two_path_scan
from tests.storage.conftest import BUCKET, SECRET

pytestmark = pytest.mark.integration


@pytest.fixture(scope="module")
def model_url(s3_server, pixelwise_model) -> str:
    """The session's pixelwise model, saved into the bucket by :func:`save_model`: its URL."""
    model = load_model(pixelwise_model)
    url = f"s3://{BUCKET}/models/pixelwise"
    assert save_model(url, model.booster, model.card) == url
    return url


def objects_below(url: str) -> dict[str, bytes]:
    where = location(url)
    return {name: objects.read_bytes(where.joinpath(name), 2**30) or b"" for name in objects.list_files(where)}


def test_save_model__bucket_holds_the_local_files_and_loads_alike(model_url, pixelwise_model):
    """The objects are the local directory's bytes (so the card's hash holds), and the loaded model predicts
    the same depths."""
    there = objects_below(model_url)
    assert there == {name: (pixelwise_model / name).read_bytes() for name in (MODEL_FILE, CARD_FILE)}
    remote, local = mpi_lidar.load_model(model_url), load_model(pixelwise_model)
    assert remote.card.to_json() == local.card.to_json() == read_card(f"{model_url}/{CARD_FILE}").to_json()
    raw = np.random.default_rng(0).uniform(0.1, 1.0, size=(64, len(local.card.raw_feature_names)))
    assert np.array_equal(remote.predict_depth(raw), local.predict_depth(raw))


def test_model_in_bucket__requests_bounded(model_url):
    """A load reads the card and the model whole, once each (a HEAD for the size each, refused above its
    bound); a save lists the location once (is a model there?) and puts the two objects, no more."""
    install_counters()
    take_counters()
    model = load_model(model_url)
    loaded = {name: n for name, n in take_counters().items() if name in OPERATIONS}
    save_model(f"s3://{BUCKET}/models/counted", model.booster, model.card)
    saved = {name: n for name, n in take_counters().items() if name in OPERATIONS}
    assert loaded == {"HeadObject": 2, "GetObject": 2}, loaded
    assert saved == {"ListObjectsV2": 1, "PutObject": 2}, saved


def test_save_model__never_over_a_model_in_the_bucket(model_url):
    model = load_model(model_url)
    with pytest.raises(MpiLidarError, match=f"model directory {model_url} already exists; choose another"):
        save_model(model_url, model.booster, model.card)
    # A publication killed after model.ubj, before its card: no model, and the next save writes it whole.
    url = f"s3://{BUCKET}/models/half"
    objects.write_object(location(url).joinpath(MODEL_FILE), b"half an upload")
    with pytest.raises(MpiLidarError, match=f"{url} is not a published model directory"):
        load_model(url)
    save_model(url, model.booster, model.card)
    assert load_model(url).card.to_json() == model.card.to_json()


def test_staged_model__second_writer_cannot_publish(model_url, tmp_path):
    """Of two savings into one URL, the one whose card comes second is refused (conditional create), and the
    first one's model stays whole."""
    model = load_model(model_url)
    url = f"s3://{BUCKET}/models/raced"
    with pytest.raises(MpiLidarError, match="written meanwhile by another process"):
        with staged_model(url) as staging:
            save_model(staging, model.booster, model.card)
            save_model(url, model.booster, model.card)  # the other writer, done first
    assert load_model(url).card.to_json() == model.card.to_json()


def test_load_model__damaged_or_pickled_in_bucket_refused(model_url):
    there = objects_below(model_url)
    edited = f"s3://{BUCKET}/models/edited"
    objects.write_object(location(edited).joinpath(MODEL_FILE), there[MODEL_FILE][:-1] + b"\0")
    objects.write_object(location(edited).joinpath(CARD_FILE), there[CARD_FILE])
    with pytest.raises(MpiLidarError, match=f"{edited}/{MODEL_FILE} does not match the hash in its card"):
        load_model(edited)
    # A pickle with a card that names its hash: XGBoost's reader refuses it, nothing unpickles it.
    pickled, payload = f"s3://{BUCKET}/models/pickled", pickle.dumps({"booster": "not a model"})
    card = json.loads(there[CARD_FILE]) | {"model_sha256": hashlib.sha256(payload).hexdigest()}
    objects.write_object(location(pickled).joinpath(MODEL_FILE), payload)
    objects.write_object(location(pickled).joinpath(CARD_FILE), json.dumps(card).encode())
    with pytest.raises(MpiLidarError, match=f"{pickled}/{MODEL_FILE} is not a readable XGBoost model"):
        load_model(pickled)
    with pytest.raises(MpiLidarError, match=f"s3://{BUCKET}/models/none is not a published model directory"):
        load_model(f"s3://{BUCKET}/models/none")


def test_correct__with_model_in_bucket_as_with_local_model(model_url, pixelwise_model, tmp_path, monkeypatch,
                                                           capsys, caplog):
    write_scan(two_path_scan("frame", seed=2), tmp_path / "frame.scan.zarr")
    runs = {}
    for name, model in (("bucket", model_url), ("local", str(pixelwise_model))):
        code, stdout, err = call_main(monkeypatch, capsys, "correct", tmp_path / "frame.scan.zarr", "--model", model,
                                      "--out", tmp_path / name, "--outputs", "data", "--gate", "all")
        assert code == 0 and "1 corrected" in stdout, stdout + err
        runs[name] = zarr.open_group(tmp_path / name / "frame" / "corrected.zarr", mode="r")
        assert SECRET not in stdout + err + caplog.text
    depth = {name: np.asarray(group["corrected_depth"][...]) for name, group in runs.items()}
    assert np.array_equal(depth["bucket"], depth["local"], equal_nan=True)
    code, _, err = call_main(monkeypatch, capsys, "correct", tmp_path / "frame.scan.zarr", "--model",
                             f"s3://{BUCKET}/models/none", "--out", tmp_path / "none")
    assert code == 2 and f"s3://{BUCKET}/models/none is not a published model directory" in err, err
