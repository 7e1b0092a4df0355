"""Datasets simulated into, and trained from, a bucket; scans imported into one (moto's S3 server on 127.0.0.1)."""

from __future__ import annotations

import json

import numpy as np
import pytest

from mpi_lidar.config import Config, PriorConfig
from mpi_lidar.errors import StoreError
from mpi_lidar.locations import location
from mpi_lidar.scans.store import read_scan
from mpi_lidar.simulation import dataset
from mpi_lidar.storage import objects
from mpi_lidar.workflows.generate import generate
from tests.cli_runner import call_main
from tests.scan_factory import two_path_scan
from tests.storage.conftest import BUCKET, SECRET

pytestmark = pytest.mark.integration

SMALL = "[dataset]\nsamples = 1200\nchunk_rows = 400\nseed = 3\n"


@pytest.mark.slow
def test_simulate__dataset_in_bucket_identical_to_local_and_trained_from(s3_server, tmp_path, monkeypatch, capsys):
    (tmp_path / "small.toml").write_text(SMALL)
    url = f"s3://{BUCKET}/datasets/d.zarr"
    code, stdout, err = call_main(monkeypatch, capsys, "simulate", "--out", url, "--config", tmp_path / "small.toml",
                                  "--workers", "0")
    assert code == 0 and f"dataset {url}: 1,200 rows" in stdout, stdout + err
    code, stdout, _ = call_main(monkeypatch, capsys, "simulate", "--out", url, "--config", tmp_path / "small.toml",
                                "--workers", "0")
    assert code == 0 and "0 of 3 chunks simulated" in stdout, stdout  # complete: every chunk kept
    config = dataset.store_config(dataset.open_store(url))
    generate(tmp_path / "d.zarr", config)
    there, here = dataset.read_verified(url), dataset.read_verified(tmp_path / "d.zarr")
    assert all(np.array_equal(there[name], here[name]) for name in dataset.DATA_ARRAYS)
    (tmp_path / "params.json").write_text('{"max_depth": 2, "learning_rate": 0.5}')
    code, stdout, err = call_main(monkeypatch, capsys, "train", "--data", url, "--out", tmp_path / "model",
                                  "--params", tmp_path / "params.json", "--workers", "0")
    assert code == 0, stdout + err
    card = json.loads((tmp_path / "model" / "card.json").read_text())
    assert url in json.dumps(card) and SECRET not in json.dumps(card) + stdout + err


def test_create_store__half_made_layout_in_bucket_is_no_store_and_is_made_again(s3_server):
    """The layout's root metadata is written last: a creation killed before it leaves no store, and the next
    creation makes it whole."""
    config = Config(prior=PriorConfig()).replace(dataset={"samples": 100, "chunk_rows": 50, "seed": 1})
    where = location(f"s3://{BUCKET}/datasets/half.zarr")
    dataset.create_store(where.url, config)
    objects.filesystem(where).rm_file(f"{where.path}/zarr.json")  # as if killed before the last write
    with pytest.raises(StoreError, match="does not exist"):
        dataset.open_store(where.url)
    group = dataset.create_store(where.url, config)
    assert dataset.incomplete_chunks(group) == [0, 1]
    assert dataset.write_chunk(where.url, config, 1) and dataset.incomplete_chunks(dataset.open_store(where.url)) == [0]


def test_import_scan__into_bucket_reads_as_local_import(s3_server, tmp_path, monkeypatch, capsys):
    scan = two_path_scan("frame", seed=4)
    for name in ("a", "b"):
        np.savez(tmp_path / f"{name}.npz", depth=scan.depth, amplitude=scan.amplitude,
                 frequencies_hz=np.asarray(scan.frequencies_hz))
    out = f"s3://{BUCKET}/imported"
    code, stdout, err = call_main(monkeypatch, capsys, "import-scan", tmp_path / "a.npz", "--out", out)
    assert code == 0 and f"written to {out}/a.scan.zarr" in stdout, stdout + err
    code, stdout, err = call_main(monkeypatch, capsys, "import-scan", tmp_path / "a.npz", tmp_path / "b.npz",
                                  "--out", out)
    assert code == 0 and "already exist" in err and f"{out}/b.scan.zarr" in stdout, stdout + err
    assert call_main(monkeypatch, capsys, "import-scan", tmp_path / "a.npz", "--out", tmp_path / "local")[0] == 0
    there, here = read_scan(f"{out}/a.scan.zarr"), read_scan(tmp_path / "local" / "a.scan.zarr")
    assert there.content_sha256() == here.content_sha256()
    code, _, err = call_main(monkeypatch, capsys, "import-scan", tmp_path / "a.npz", "--out", out)
    assert code == 2 and "already exists" in err, err
