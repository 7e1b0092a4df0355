"""Dask clusters: a LocalCluster of worker processes by default, or a running scheduler by address."""

from __future__ import annotations

import logging
from collections.abc import Iterator
from contextlib import contextmanager

from distributed import Client, LocalCluster

from mpi_lidar.errors import MpiLidarError

CONNECT_TIMEOUT_S = 20


@contextmanager
def dask_client(scheduler: str | None = None, workers: int = 2) -> Iterator[Client]:
    """A Dask client for the run.

    Parameters
    ----------
    scheduler : Address of a running scheduler (``tcp://host:8786``); None starts a LocalCluster.
    workers : Worker processes of the LocalCluster, one thread each (numpy does the inner parallelism); 0 runs
        one worker thread in this process (for libraries such as ``xgboost.dask`` that need a cluster).
    """
    if scheduler:
        try:
            client = Client(scheduler, timeout=CONNECT_TIMEOUT_S)
        except (OSError, TimeoutError) as exc:
            raise MpiLidarError(
                f"cannot reach the Dask scheduler at {scheduler} ({type(exc).__name__}); start it with "
                "'dask scheduler' and 'dask worker', or leave out --scheduler to use a local cluster"
            ) from None
        with client:
            yield client
        return
    if workers < 0:
        raise MpiLidarError(f"--workers must be 0 (this process) or more, got {workers}")
    # Task errors reach the caller as exceptions and are reported once; the workers' own ERROR log lines
    # about the same failure would only flood the terminal.
    with (
        LocalCluster(n_workers=max(workers, 1), threads_per_worker=1, processes=workers > 0, dashboard_address=":0",
                     silence_logs=logging.CRITICAL) as cluster,
        Client(cluster) as client,
    ):
        yield client
