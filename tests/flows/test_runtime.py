"""One Prefect API for the flow process and its Dask workers."""

from __future__ import annotations

import os

import pytest
from prefect.context import serialize_context
from prefect.server.api.server import SubprocessASGIServer
from prefect.settings import PREFECT_API_URL, get_current_settings, temporary_settings

from flows.runtime import api_url, dask_task_runner, describe_workers, shared_api
from mpi_lidar.errors import MpiLidarError


def test_shared_api__exports_url_to_settings_and_environment(prefect_api: str) -> None:
    with shared_api() as url:
        assert url == prefect_api
        assert os.environ["PREFECT_API_URL"] == url
        assert get_current_settings().api.url == url


def test_api_url__without_configured_url_reuses_the_default_temporary_server(prefect_api: str) -> None:
    """The server ephemeral clients start (``SubprocessASGIServer()``) is the one the session uses: no second."""
    with temporary_settings(restore_defaults={PREFECT_API_URL}):
        assert get_current_settings().api.url is None
        assert api_url() == (prefect_api, False)
    assert SubprocessASGIServer().api_url == prefect_api


def test_shared_api__ephemeral_mode_ships_one_url_to_tasks(prefect_api: str, monkeypatch: pytest.MonkeyPatch) -> None:
    """With no URL configured, both channels to a Dask worker carry the default temporary server's URL."""
    monkeypatch.delenv("PREFECT_API_URL")
    with temporary_settings(restore_defaults={PREFECT_API_URL}):
        with shared_api() as url:
            shipped = serialize_context()["settings_context"]["settings"]["api"]["url"]
            assert url == prefect_api and shipped == url and os.environ["PREFECT_API_URL"] == url
        assert "PREFECT_API_URL" not in os.environ


def test_shared_api__dask_workers_inherit_the_url(dask_scheduler: str, prefect_api: str) -> None:
    from distributed import Client

    with Client(dask_scheduler) as client:
        seen = client.run(os.environ.get, "PREFECT_API_URL")
    assert seen and set(seen.values()) == {prefect_api}


def test_dask_task_runner__local_cluster_or_scheduler_address() -> None:
    local = dask_task_runner(workers=3)
    assert local.cluster_kwargs["n_workers"] == 3 and local.cluster_kwargs["threads_per_worker"] == 1
    assert dask_task_runner(scheduler="tcp://10.0.0.1:8786").address == "tcp://10.0.0.1:8786"
    with pytest.raises(MpiLidarError, match="at least 1"):
        dask_task_runner(workers=0)


def test_describe_workers__names_the_cluster() -> None:
    assert describe_workers(2, None) == "LocalCluster, 2 processes x 1 thread"
    assert describe_workers(1, None) == "LocalCluster, 1 process x 1 thread"
    assert describe_workers(2, "tcp://h:8786") == "Dask scheduler tcp://h:8786"
