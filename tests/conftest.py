"""Fixtures shared by the suite, and the one rule of its split into unit and integration tests.

Every test carries exactly one of two marks, registered in pyproject.toml:

- ``unit``: pure functions and in-process runs on small inputs (corrections included, with a model trained in
  the process in about a second, ``tests/model_factory.py``); ``make test-quick`` runs only these
  (``pytest -m unit -n 2``), in two to three minutes.
- ``integration``: starts a Dask cluster, Prefect, PostgreSQL, a subprocess or a browser, trains a model through
  a cluster, runs a benchmark, or takes more than a few seconds; those that take more than a few seconds also
  carry ``slow``.

A test says its kind itself (``@pytest.mark.unit``), through its class, or through its module
(``pytestmark = pytest.mark.unit``); tests/integration/ and tests/flows/ mark everything in them from their own
conftest.py (:func:`mark_directory`). There is no list of names and no rule by fixture: a test with neither mark,
with both, or ``slow`` and ``unit``, stops the collection with a usage error that names it, so nothing is
sorted silently.
"""

from __future__ import annotations

import os
import uuid
from collections.abc import Iterable
from pathlib import Path

import numpy as np
import pytest

from mpi_lidar.config import Config, PriorConfig

POSTGRES_ADMIN_URL = os.environ.get("MPI_LIDAR_TEST_POSTGRES", "postgresql://postgres@127.0.0.1:5432/postgres")

KINDS = ("unit", "integration")
FLOWS_DIRECTORY = "tests/flows"  # node ids are relative to the root directory


def marker_kind(item: pytest.Item) -> str:
    """``"unit"`` or ``"integration"``: the one of the two marks ``item`` carries (its own, its class's, its
    module's or its directory's).

    Raises
    ------
    pytest.UsageError
        Where it carries neither or both, or ``slow`` with ``unit``.
    """
    marks = {mark.name for mark in item.iter_markers()}
    kinds = [kind for kind in KINDS if kind in marks]
    if len(kinds) != 1:
        said = "both unit and integration" if kinds else "neither unit nor integration"
        raise pytest.UsageError(f"{item.nodeid} is marked {said}: mark the test or its module "
                                "(pytestmark = pytest.mark.unit), see tests/conftest.py")
    if kinds == ["unit"] and "slow" in marks:
        raise pytest.UsageError(f"{item.nodeid} is marked slow and unit: a slow test is an integration test")
    return kinds[0]


def mark_directory(items: Iterable[pytest.Item], directory: Path, kind: str) -> None:
    """Mark every item collected from below ``directory`` with ``kind`` (a directory conftest's
    ``pytest_collection_modifyitems``, which sees the items of the whole session)."""
    for item in items:
        if Path(str(item.path)).resolve().is_relative_to(directory):
            item.add_marker(kind)


def pytest_collection_modifyitems(items: list[pytest.Item]) -> None:
    """Refuse the session where any test is not exactly one kind. Runs after the directories' conftests (theirs
    are ``tryfirst``) and before ``-m`` deselects anything, so a test without its mark cannot drop out of
    ``-m unit`` unseen."""
    refused = []
    for item in items:
        try:
            marker_kind(item)
        except pytest.UsageError as error:
            refused.append(str(error))
    if refused:
        shown = "\n".join(refused[:20]) + (f"\n... and {len(refused) - 20} more" if len(refused) > 20 else "")
        raise pytest.UsageError(f"{len(refused)} test(s) without exactly one of unit/integration:\n{shown}")
    items[:] = slow_files_first(items)


@pytest.hookimpl(tryfirst=True, optionalhook=True)
def pytest_xdist_make_scheduler(config: pytest.Config, log: object) -> object | None:
    """With ``--dist loadfile`` (``make test``), whole files go to a worker, and tests/flows/ as one: its files
    share the session's Prefect API server (tests/flows/conftest.py), which a second worker would start again."""
    if config.getvalue("dist") != "loadfile":
        return None
    from xdist.scheduler import LoadFileScheduling

    class SharedServerFiles(LoadFileScheduling):
        def _split_scope(self, nodeid: str) -> str:
            path = super()._split_scope(nodeid)
            return FLOWS_DIRECTORY if path.startswith(f"{FLOWS_DIRECTORY}/") else path

    return SharedServerFiles(config, log)


def slow_files_first(items: list[pytest.Item]) -> list[pytest.Item]:
    """The items of files holding a ``slow`` test first, each file's items together and in their order.

    ``make test`` hands whole files to two worker processes in collection order (``--no-loadscope-reorder``),
    the next file to whichever is free: with the long files started first, the short ones fill the gaps at the
    end instead of one worker finishing a long file while the other waits.
    """
    slow_paths = {item.path for item in items if item.get_closest_marker("slow")}
    return sorted(items, key=lambda item: item.path not in slow_paths)  # stable: the order within each group stays


@pytest.fixture
def config() -> Config:
    return Config()


@pytest.fixture
def rng() -> np.random.Generator:
    return np.random.default_rng(12345)


@pytest.fixture(scope="session")
def cluster_client():
    """One two-worker LocalCluster (worker processes, one thread each) shared by the session."""
    from distributed import Client, LocalCluster

    with LocalCluster(n_workers=2, threads_per_worker=1, processes=True, dashboard_address=":0") as cluster:
        with Client(cluster) as client:
            yield client


@pytest.fixture(scope="session")
def small_dataset(tmp_path_factory) -> Path:
    """A complete 8,000-row dataset (6,400 train, 1,600 test) of the paper's prior (d_AS 1.4-2.4 m): small
    models learn it well enough for the tests' scans at about 2 m, and its range rule is theirs."""
    from mpi_lidar.workflows.generate import generate

    path = tmp_path_factory.mktemp("small") / "dataset.zarr"
    generate(path, Config(prior=PriorConfig()).replace(dataset={"samples": 8_000, "chunk_rows": 2_000, "seed": 11}))
    return path


@pytest.fixture
def postgres_url():
    """A fresh PostgreSQL database on the local server, dropped afterwards."""
    import psycopg

    name = f"mpi_lidar_test_{uuid.uuid4().hex[:10]}"
    with psycopg.connect(POSTGRES_ADMIN_URL, autocommit=True) as admin:
        admin.execute(f'CREATE DATABASE "{name}"')
    yield POSTGRES_ADMIN_URL.rsplit("/", 1)[0] + f"/{name}"
    with psycopg.connect(POSTGRES_ADMIN_URL, autocommit=True) as admin:
        admin.execute(f'DROP DATABASE IF EXISTS "{name}" WITH (FORCE)')


@pytest.fixture(scope="session")
def pixelwise_model(tmp_path_factory) -> Path:
    """A residual model of the raw features (no geometric inputs) trained in this process in about a second on
    the paper's prior (d_AS 1.4-2.4 m), the prior of the tests' scans and range rules: what the correction tests
    correct with, as unit tests."""
    from tests.model_factory import tiny_model

    return tiny_model(tmp_path_factory.mktemp("pixelwise") / "model", geometric=False, feature_set="raw")


@pytest.fixture(scope="session")
def small_model(tmp_path_factory, cluster_client, small_dataset) -> Path:
    """A quickly trained residual model on the small dataset (through xgboost.dask): for the tests of a model
    trained on a cluster; the others correct with :func:`pixelwise_model`."""
    from mpi_lidar.learning.features import FeatureSpec
    from mpi_lidar.learning.train import train_and_save

    params = {"max_depth": 6, "learning_rate": 0.3, "subsample": 1.0, "colsample_bytree": 1.0,
              "min_child_weight": 1.0, "reg_lambda": 1.0, "gamma": 0.0}
    out, _ = train_and_save(cluster_client, small_dataset, tmp_path_factory.mktemp("model") / "model",
                            FeatureSpec(Config().frequencies_hz, "raw", "residual"), params,
                            num_boost_round=150, early_stopping_rounds=10)
    return out
