from __future__ import annotations

import os
import uuid
from pathlib import Path

import numpy as np
import pytest
from distributed import Client, LocalCluster

from mpi_lidar.config import Config
from mpi_lidar.workflows.generate import generate

POSTGRES_ADMIN_URL = os.environ.get("MPI_LIDAR_TEST_POSTGRES", "postgresql://postgres@127.0.0.1:5432/postgres")


@pytest.fixture
def config() -> Config:
    return Config()


@pytest.fixture
def rng() -> np.random.Generator:
    return np.random.default_rng(12345)


@pytest.fixture(scope="session")
def cluster_client():
    """One two-worker LocalCluster (worker processes, one thread each) shared by the session."""
    with LocalCluster(n_workers=2, threads_per_worker=1, processes=True, dashboard_address=":0") as cluster:
        with Client(cluster) as client:
            yield client


@pytest.fixture(scope="session")
def small_dataset(tmp_path_factory) -> Path:
    """A complete 8,000-row dataset of the default configuration (6,400 train, 1,600 test)."""
    path = tmp_path_factory.mktemp("small") / "dataset.zarr"
    generate(path, Config().replace(dataset={"samples": 8_000, "chunk_rows": 2_000, "seed": 11}))
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
def small_model(tmp_path_factory, cluster_client, small_dataset) -> Path:
    """A quickly trained residual model on the small dataset (through xgboost.dask)."""
    from mpi_lidar.learning.features import FeatureSpec
    from mpi_lidar.learning.train import train_and_save

    params = {"max_depth": 6, "learning_rate": 0.3, "subsample": 1.0, "colsample_bytree": 1.0,
              "min_child_weight": 1.0, "reg_lambda": 1.0, "gamma": 0.0}
    out, _ = train_and_save(cluster_client, small_dataset, tmp_path_factory.mktemp("model") / "model",
                            FeatureSpec(Config().frequencies_hz, "raw", "residual"), params,
                            num_boost_round=150, early_stopping_rounds=10)
    return out
