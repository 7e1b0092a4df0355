"""Scheduled regeneration: one store per configuration and code version, skipped when complete."""

from __future__ import annotations

import hashlib
import os
from pathlib import Path

import pytest

from flows import generate_dataset
from flows.regenerate import point_latest_task, regenerate_dataset_flow
from mpi_lidar import __version__
from mpi_lidar.config import config_sha256, resolve_config
from mpi_lidar.errors import StoreError
from mpi_lidar.simulation import dataset
from mpi_lidar.simulation.dataset import store_key
from tests.flows.helpers import CHUNKS, SEED, chunk_task_runs, subflow_runs, write_config


def fingerprint(directory: Path) -> dict[str, tuple[int, str]]:
    """Modification time and content hash of every file under ``directory``."""
    return {
        str(path.relative_to(directory)): (path.stat().st_mtime_ns, hashlib.sha256(path.read_bytes()).hexdigest())
        for path in sorted(directory.rglob("*")) if path.is_file()
    }


@pytest.fixture(scope="module")
def first_run(tmp_path_factory: pytest.TempPathFactory, config_file: Path, dask_scheduler: str) -> dict[str, object]:
    """The first regeneration of a fresh root, on the session's running Dask cluster."""
    root = tmp_path_factory.mktemp("nightly")
    return regenerate_dataset_flow(root=str(root), config_file=str(config_file), scheduler=dask_scheduler)


@pytest.mark.slow
def test_regenerate_dataset_flow__first_run_generates_into_key_directory(
    first_run: dict[str, object], config_file: Path, dask_scheduler: str
) -> None:
    config = resolve_config(config_file, "quick")
    expected_key = hashlib.sha256((config_sha256(config) + __version__).encode()).hexdigest()[:16]
    assert first_run["skipped"] is False
    assert first_run["key"] == expected_key
    assert Path(first_run["path"]).parts[-2:] == (expected_key, "dataset.zarr")
    assert first_run["generation"]["chunks_written"] == CHUNKS
    assert dataset.dataset_info(first_run["path"]).complete
    assert os.path.samefile(first_run["latest"], Path(first_run["path"]).parent)


def test_regenerate_dataset_flow__complete_store_skips_all_work(
    first_run: dict[str, object], config_file: Path, dask_scheduler: str, monkeypatch: pytest.MonkeyPatch
) -> None:
    def no_cluster(*_args: object) -> None:
        raise AssertionError("a complete store must not start a Dask cluster")

    monkeypatch.setattr(generate_dataset, "dask_task_runner", no_cluster)
    root = Path(first_run["path"]).parents[1]
    before = fingerprint(Path(first_run["path"]))
    again = regenerate_dataset_flow(root=str(root), config_file=str(config_file), scheduler=dask_scheduler)
    assert again["skipped"] is True and again["generation"] is None
    assert again["path"] == first_run["path"]
    assert subflow_runs(again["flow_run_id"]) == []
    assert chunk_task_runs(again["flow_run_id"]) == []
    assert fingerprint(Path(first_run["path"])) == before
    assert Path(again["latest"]).readlink() == Path(first_run["key"])


@pytest.mark.slow
def test_regenerate_dataset_flow__new_seed_gets_new_store_and_keeps_old(
    first_run: dict[str, object], dask_scheduler: str, tmp_path: Path
) -> None:
    root = Path(first_run["path"]).parents[1]
    old_store = Path(first_run["path"])
    before = fingerprint(old_store)
    other = write_config(tmp_path / "other-seed.toml", seed=SEED + 1)
    second = regenerate_dataset_flow(root=str(root), config_file=str(other), scheduler=dask_scheduler)
    assert second["skipped"] is False and second["key"] != first_run["key"]
    assert dataset.dataset_info(second["path"]).config.dataset.seed == SEED + 1
    assert fingerprint(old_store) == before
    assert os.path.samefile(root / "latest", Path(second["path"]).parent)


def test_store_key__changes_with_config_and_version(config_file: Path) -> None:
    config = resolve_config(config_file, "quick")
    key = store_key(config, "0.1.0")
    assert len(key) == 16 and int(key, 16) >= 0
    assert store_key(config, "0.2.0") != key
    assert store_key(config.replace(dataset={"seed": 1}), "0.1.0") != key


def test_point_latest_task__replaces_link_and_refuses_a_real_directory(tmp_path: Path) -> None:
    (tmp_path / "a").mkdir()
    (tmp_path / "b").mkdir()
    point_latest_task.fn(str(tmp_path), "a")
    point_latest_task.fn(str(tmp_path), "b")
    assert (tmp_path / "latest").readlink() == Path("b")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a", "b", "latest"]  # no staging link left behind
    (tmp_path / "latest").unlink()
    (tmp_path / "latest").mkdir()
    with pytest.raises(StoreError, match="not a symlink"):
        point_latest_task.fn(str(tmp_path), "a")
