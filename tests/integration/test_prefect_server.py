"""A real ``prefect server start``: the deployments are served, one run is triggered through the API and checked."""

from __future__ import annotations

import os
import time
import urllib.request
from collections.abc import Iterator
from pathlib import Path

import pytest

from mpi_lidar.simulation import dataset
from tests.integration.conftest import BIN, REPO, free_port, stop_group, subprocess_env

pytestmark = pytest.mark.slow

SERVER_START_S = 180
RUN_TIMEOUT_S = 400


def prefect_env(home: Path, api_url: str) -> dict[str, str]:
    return subprocess_env(
        PREFECT_HOME=str(home), PREFECT_API_URL=api_url, PREFECT_SERVER_ANALYTICS_ENABLED="false",
        PREFECT_LOGGING_LEVEL="WARNING", PREFECT_SERVER_EPHEMERAL_STARTUP_TIMEOUT_SECONDS="180",
        # No UI to copy into the fresh PREFECT_HOME (the API alone is tested), and the served runner asks for
        # scheduled runs every second instead of every 10 s.
        PREFECT_SERVER_UI_ENABLED="false", PREFECT_RUNNER_POLL_FREQUENCY="1",
    )


def wait_until(ready, timeout_s: float, what: str, process=None, log: Path | None = None) -> None:
    deadline = time.monotonic() + timeout_s
    while not ready():
        tail = log.read_text()[-3000:] if log else ""
        if process is not None and process.poll() is not None:
            raise AssertionError(f"{what}: process exited {process.returncode}: {tail}")
        if time.monotonic() > deadline:
            raise AssertionError(f"{what}: not ready after {timeout_s} s: {tail}")
        time.sleep(0.2)


def healthy(api_url: str) -> bool:
    try:
        with urllib.request.urlopen(f"{api_url}/health", timeout=5) as response:
            return response.status == 200
    except OSError:
        return False


@pytest.fixture(scope="module")
def prefect_server(tmp_path_factory: pytest.TempPathFactory) -> Iterator[tuple[str, Path]]:
    """``prefect server start`` on 127.0.0.1 with its own PREFECT_HOME (SQLite); yields its API URL and home.

    The API alone (``--no-services``): the run is triggered through it and the served runner polls it for the
    run, so none of the background services (schedules expanded into runs, late runs, event triggers) take
    part, and they would take the two cores from the run.
    """
    import subprocess

    home = tmp_path_factory.mktemp("prefect-home")
    port = free_port()
    api_url = f"http://127.0.0.1:{port}/api"
    log = home / "server.log"
    process = subprocess.Popen(
        [str(BIN / "prefect"), "server", "start", "--host", "127.0.0.1", "--port", str(port), "--no-services"],
        stdout=log.open("w"), stderr=subprocess.STDOUT, env=prefect_env(home, api_url), cwd=REPO,
        start_new_session=True)
    try:
        wait_until(lambda: healthy(api_url), SERVER_START_S, "prefect server", process, log)
        yield api_url, home
    finally:
        stop_group(process, sig=2)


def test_served_deployments__triggered_regeneration_completes_with_artifacts(
    tmp_path: Path, prefect_server: tuple[str, Path]
) -> None:
    import subprocess

    from prefect import get_client
    from prefect.client.schemas.filters import ArtifactFilter, ArtifactFilterKey
    from prefect.settings import PREFECT_API_URL, temporary_settings

    api_url, home = prefect_server
    config = tmp_path / "tiny.toml"
    config.write_text("[dataset]\nsamples = 2000\nchunk_rows = 500\nseed = 3\n")
    root = tmp_path / "nightly"
    log = tmp_path / "serve.log"
    served = subprocess.Popen(
        [str(BIN / "python"), "-m", "flows.deploy", "--root", str(root), "--workers", "1"],
        stdout=log.open("w"), stderr=subprocess.STDOUT, env=prefect_env(home, api_url), cwd=REPO,
        start_new_session=True)
    try:
        with temporary_settings(updates={PREFECT_API_URL: api_url}), get_client(sync_client=True) as client:
            names = ["regenerate-dataset/nightly-regeneration", "tune/tune", "train/train",
                     "correct-archive/correct-archive"]

            def registered() -> bool:
                return len(client.read_deployments()) >= len(names)

            wait_until(registered, SERVER_START_S, "flows.deploy", served, log)
            deployments = {name: client.read_deployment_by_name(name) for name in names}
            nightly = deployments["regenerate-dataset/nightly-regeneration"]
            assert [s.schedule.cron for s in nightly.schedules] == ["0 2 * * *"]
            assert all(s.active for s in nightly.schedules)

            run = client.create_flow_run_from_deployment(nightly.id, parameters={"config_file": str(config)})
            wait_until(lambda: client.read_flow_run(run.id).state.is_final(), RUN_TIMEOUT_S, "flow run", served, log)
            final = client.read_flow_run(run.id)
            assert final.state.is_completed(), f"{final.state}: {log.read_text()[-3000:]}"
            assert final.parameters["root"] == str(root) and final.parameters["workers"] == 1
            summaries = client.read_artifacts(artifact_filter=ArtifactFilter(key=ArtifactFilterKey(
                any_=["dataset-summary"])))
    finally:
        stop_group(served, sig=2)
    assert len(summaries) == 1 and "31.25" in str(summaries[0].data)
    store = root / "latest" / "dataset.zarr"
    assert dataset.dataset_info(store).complete and dataset.dataset_info(store).samples == 2000
    assert os.path.realpath(root / "latest") == str((root / dataset.store_key(
        dataset.dataset_info(store).config)).resolve())
