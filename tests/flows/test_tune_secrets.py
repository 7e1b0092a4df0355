"""The tune flow never takes a password as a parameter: Prefect stores and shows flow-run parameters in clear.

A ``storage`` that carries one fails the run before anything connects, and the run's recorded parameters hold
it masked; the password reaches the flow from the environment or a Prefect Secret block instead."""

from __future__ import annotations

import uuid
from urllib.parse import quote

import pytest
from prefect import get_client
from prefect.blocks.system import Secret

from flows.tune import flow_storage, tune_flow
from mpi_lidar.errors import ConfigError
from mpi_lidar.learning.tune import STORAGE_URL_VARIABLE

SECRET = "Zq-flow-s3cret"


@pytest.mark.parametrize("storage", [
    f"postgresql://postgres:{SECRET}@127.0.0.1:5432/postgres",
    f"postgresql+psycopg://postgres@127.0.0.1:5432/postgres?password={SECRET}",
    f"postgresql://postgres:{quote(SECRET + '@/', safe='')}@127.0.0.1/postgres",
    f"postgresql://postgres:{SECRET}@x@127.0.0.1/postgres",
])
def test_tune_flow__password_in_storage_fails_and_is_never_recorded(tmp_path, storage):
    state = tune_flow(data=str(tmp_path / "d.zarr"), storage=storage, trials=1, workers=0, return_state=True)
    assert state.is_failed()
    assert "carries a password" in state.message and SECRET not in state.message
    with get_client(sync_client=True) as client:
        run = client.read_flow_run(state.state_details.flow_run_id)
    recorded = str(run.parameters)
    assert SECRET not in recorded and "***" in recorded
    assert not (tmp_path / "optuna.db").exists()


def test_flow_storage__secret_block_environment_and_password_free_urls(tmp_path, monkeypatch):
    data = str(tmp_path / "d.zarr")
    with_password = f"postgresql://postgres:{SECRET}@127.0.0.1:5432/postgres"
    name = f"mpi-lidar-storage-{uuid.uuid4().hex[:8]}"
    Secret(value=with_password).save(name)
    assert flow_storage(None, name, data) == with_password
    monkeypatch.setenv(STORAGE_URL_VARIABLE, with_password)
    assert flow_storage(None, None, data) == with_password
    without = "postgresql://postgres@127.0.0.1:5432/postgres"  # PGPASSWORD or ~/.pgpass give the password
    assert flow_storage(without, name, data) == without
    with pytest.raises(ConfigError, match="Prefect Secret block 'no-such-block' cannot be loaded"):
        flow_storage(None, "no-such-block", data)
    with pytest.raises(ConfigError, match="MPI_LIDAR_STORAGE_URL") as refused:
        flow_storage(with_password, None, data)
    assert SECRET not in str(refused.value)
