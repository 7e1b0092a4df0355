"""Malformed scan and dataset stores: each fails with one clear MpiLidarError line, and a batch goes on."""

from __future__ import annotations

import json
import shutil
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest
import zarr

from mpi_lidar.correction import CorrectionOptions
from mpi_lidar.errors import MpiLidarError
from mpi_lidar.scans.store import read_scan, write_scan
from mpi_lidar.simulation import dataset
from mpi_lidar.workflows.correct_archive import correct_archive
from tests.scan_factory import two_path_scan

HEIGHT, WIDTH = 12, 16


def edit_json(path: Path, change: Callable[[dict], None]) -> None:
    meta = json.loads(path.read_text())
    change(meta)
    path.write_text(json.dumps(meta))


def replace_array(store: Path, name: str, data: np.ndarray) -> None:
    group = zarr.open_group(str(store), mode="r+")
    del group[name]
    group.create_array(name, data=data)


def first_chunk(store: Path, name: str) -> Path:
    return next(p for p in sorted((store / name / "c").rglob("*")) if p.is_file())


def _set_attr(store: Path, key: str, value: object) -> None:
    edit_json(store / "zarr.json", lambda meta: meta["attributes"].__setitem__(key, value))


def _drop_attr(store: Path, key: str) -> None:
    edit_json(store / "zarr.json", lambda meta: meta["attributes"].pop(key))


def _declare_shape(store: Path, name: str, shape: list[int]) -> None:
    edit_json(store / name / "zarr.json", lambda meta: meta.__setitem__("shape", shape))


def _truncate(path: Path) -> None:
    path.write_bytes(path.read_bytes()[:7])


SCAN_DAMAGE: dict[str, Callable[[Path], None]] = {
    "integer depth": lambda s: replace_array(s, "depth", np.ones((4, HEIGHT, WIDTH), np.int16)),
    "2-D depth": lambda s: replace_array(s, "depth", np.ones((HEIGHT, WIDTH), np.float32)),
    "amplitude shape": lambda s: replace_array(s, "amplitude", np.ones((4, HEIGHT, WIDTH + 1), np.float32)),
    "negative amplitude": lambda s: replace_array(s, "amplitude", -np.ones((4, HEIGHT, WIDTH), np.float32)),
    "all-NaN depth": lambda s: replace_array(s, "depth", np.full((4, HEIGHT, WIDTH), np.nan, np.float32)),
    "reference shape": lambda s: replace_array(s, "reference_depth", np.ones((HEIGHT + 1, WIDTH), np.float32)),
    "frequencies not numbers": lambda s: _set_attr(s, "frequencies_hz", ["fast", "slow"]),
    "frequencies a number": lambda s: _set_attr(s, "frequencies_hz", 12.5e6),
    "three frequencies": lambda s: _set_attr(s, "frequencies_hz", [12.5e6, 25e6, 31.25e6]),
    "negative frequency": lambda s: _set_attr(s, "frequencies_hz", [-12.5e6, 18.75e6, 25e6, 31.25e6]),
    "no frequencies": lambda s: _drop_attr(s, "frequencies_hz"),
    "foreign schema": lambda s: _set_attr(s, "schema", "someone-else@1"),
    "name escapes": lambda s: _set_attr(s, "name", "../../etc"),
    "root metadata garbage": lambda s: (s / "zarr.json").write_text("{not json"),
    "array metadata garbage": lambda s: (s / "depth" / "zarr.json").write_text("\x00\x01"),
    "truncated chunk": lambda s: _truncate(first_chunk(s, "depth")),
    "huge declared shape": lambda s: _declare_shape(s, "depth", [4, 2_000_000, 2_000_000]),
    "depth missing": lambda s: shutil.rmtree(s / "depth"),
}


@pytest.fixture(scope="module")
def good_scan(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return write_scan(two_path_scan("good", HEIGHT, WIDTH), tmp_path_factory.mktemp("good") / "good.scan.zarr")


@pytest.mark.parametrize("damage", SCAN_DAMAGE)
def test_read_scan__malformed_store_fails_with_one_clear_line(tmp_path: Path, good_scan: Path, damage: str) -> None:
    store = tmp_path / "bad.scan.zarr"
    shutil.copytree(good_scan, store)
    SCAN_DAMAGE[damage](store)
    try:
        read_scan(store)
    except MpiLidarError as error:
        message = str(error)
    else:
        assert damage == "name escapes", f"{damage}: read without error"
        return
    assert "\n" not in message and str(store) in message and len(message) < 400, message


@pytest.mark.slow
def test_correct_archive__malformed_scans_fail_alone_and_the_rest_are_corrected(
    tmp_path: Path, good_scan: Path, cluster_model: Path
) -> None:
    archive = tmp_path / "archive"
    for index, damage in enumerate(SCAN_DAMAGE):
        store = archive / f"bad{index:02d}.scan.zarr"
        shutil.copytree(good_scan, store)
        _set_attr(store, "name", f"bad{index:02d}")
        SCAN_DAMAGE[damage](store)
    for index in range(3):
        write_scan(two_path_scan(f"good{index}", HEIGHT, WIDTH, seed=index), archive / f"good{index}.scan.zarr")
    # the command line's default output level: the damaged stores fail on reading, before any output is written
    outcomes = correct_archive([str(archive)], cluster_model, tmp_path / "out", CorrectionOptions(), outputs="light")
    by_status: dict[str, list[str]] = {}
    for outcome in outcomes:
        by_status.setdefault(outcome.status, []).append(outcome.name)
        assert outcome.status != "failed" or "\n" not in outcome.reason
    assert sorted(by_status["unchanged"]) == ["good0", "good1", "good2"]  # planes: nothing to correct
    assert len(by_status["failed"]) == len(SCAN_DAMAGE)
    escaped = tmp_path / "etc"
    assert not escaped.exists() and sorted(p.name for p in (tmp_path / "out").iterdir()) == [
        "good0", "good1", "good2"]


DATASET_DAMAGE: dict[str, Callable[[Path], None]] = {
    "float64 features": lambda s: replace_array(s, "features", np.zeros((8_000, 8), np.float64)),
    "short target": lambda s: replace_array(s, "target", np.zeros(7_999, np.float64)),
    "huge declared shape": lambda s: _declare_shape(s, "features", [10**12, 8]),
    "huge declared samples": lambda s: _set_attr(s, "samples", 10**12),
    "samples not a number": lambda s: _set_attr(s, "samples", "many"),
    "frequencies a number": lambda s: _set_attr(s, "frequencies_hz", 5),
    "config garbage": lambda s: _set_attr(s, "config", {"dataset": {"samples": -3}}),
    "no chunk marks": lambda s: shutil.rmtree(s / "chunk_done"),
    "truncated chunk": lambda s: _truncate(first_chunk(s, "features")),
    "root metadata garbage": lambda s: (s / "zarr.json").write_text("[]"),
    "foreign schema": lambda s: _set_attr(s, "schema", "mpi-lidar/dataset@0"),
}


@pytest.mark.parametrize("damage", DATASET_DAMAGE)
def test_read_dataset__malformed_store_fails_with_one_clear_line(
    tmp_path: Path, small_dataset: Path, damage: str
) -> None:
    store = tmp_path / "bad.zarr"
    shutil.copytree(small_dataset, store)
    DATASET_DAMAGE[damage](store)
    with pytest.raises(MpiLidarError) as error:
        dataset.dataset_info(store)
        dataset.read_subsample(store, "all")
    message = str(error.value)
    assert "\n" not in message and str(store) in message and len(message) < 400, message
