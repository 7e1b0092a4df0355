"""One Prefect API and one small configuration for the whole test session.

:mod:`tests.flows.environment` sets the environment first (a throw-away ``PREFECT_HOME``, quiet logs). The
session then starts one temporary API server through :func:`flows.runtime.shared_api`, which puts its URL in
``PREFECT_API_URL``, so every Dask worker process started later reports to the same server.
"""

from __future__ import annotations

import logging
from collections.abc import Iterator
from pathlib import Path

import pytest

from tests.conftest import mark_directory
from tests.flows import environment  # before anything imports Prefect
from tests.flows.helpers import write_config


@pytest.hookimpl(tryfirst=True)
def pytest_collection_modifyitems(items: list[pytest.Item]) -> None:
    """Every test in this directory is an integration test (tests/conftest.py)."""
    mark_directory(items, Path(__file__).resolve().parent, "integration")


@pytest.fixture(scope="session", autouse=True)
def prefect_api() -> Iterator[str]:
    """The session's Prefect API URL: one temporary server, shared by the tests and all Dask workers."""
    from prefect.context import refresh_global_settings_context

    from flows.runtime import shared_api

    refresh_global_settings_context()  # in case Prefect was imported before the environment was set
    try:
        with shared_api(stop_started=True) as url:
            yield url
    finally:
        environment.restore()
        refresh_global_settings_context()


@pytest.fixture(scope="session")
def config_file(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return write_config(tmp_path_factory.mktemp("config") / "small.toml")


@pytest.fixture(scope="session")
def dask_scheduler(prefect_api: str) -> Iterator[str]:
    """Address of a one-worker LocalCluster started after the API URL was exported, as a real cluster would be."""
    from distributed import LocalCluster

    with LocalCluster(n_workers=1, threads_per_worker=1, processes=True, dashboard_address=None,
                      silence_logs=logging.ERROR) as cluster:
        yield cluster.scheduler_address
