"""A scheduler address is shown or stored by the flows without its password (integration: imports Prefect)."""

from __future__ import annotations

import pytest


def test_scheduler_address__password_with_separators_never_shown_or_stored():
    """Where a scheduler address is shown (a dataset's report) or stored (a deployment's flow-run parameters,
    a task runner), a password with '@', ':' and '/' in it appears nowhere: masked, or refused masked."""
    from flows.deploy import build_deployments, on_demand_deployments
    from flows.runtime import dask_task_runner, describe_workers
    from mpi_lidar.errors import MpiLidarError

    password = "p@ss:w/rd"
    address = f"tcp://user:{password}@scheduler.example.org:8786"
    assert password not in describe_workers(2, address) and "w/rd" not in describe_workers(2, address)
    for store in (lambda: dask_task_runner(2, address), lambda: build_deployments(scheduler=address),
                  lambda: on_demand_deployments(scheduler=address)):
        with pytest.raises(MpiLidarError, match="carries credentials") as refused:
            store()
        assert "p@ss" not in str(refused.value) and "w/rd" not in str(refused.value)
