"""Dask clusters: a LocalCluster of worker processes by default, or a running scheduler by address."""

from __future__ import annotations

import logging
from collections.abc import Iterator
from contextlib import contextmanager
from urllib.parse import urlsplit

from distributed import Client, LocalCluster

from mpi_lidar.errors import MpiLidarError
from mpi_lidar.redact import MASK, install_log_redaction, redact

CONNECT_TIMEOUT_S = 20


def check_scheduler_address(scheduler: str) -> str:
    """A scheduler address without credentials, as given; one that carries a user or password is refused.

    Dask addresses (``tcp://host:8786``, ``tls://host:8786``) take no user or password: a secured cluster
    authenticates with TLS certificates from Dask's configuration (``distributed.comm.tls``). A password in an
    address would only be printed and logged, so it is refused, masked.
    """
    with_scheme = scheduler if "://" in scheduler else f"tcp://{scheduler}"  # Dask's default protocol
    try:
        netloc = urlsplit(with_scheme).netloc
    except ValueError:
        netloc = scheduler
    if "@" in netloc or redact(with_scheme) != with_scheme:
        shown = redact(with_scheme) if "://" in scheduler else redact(with_scheme).removeprefix("tcp://")
        if "@" in shown and MASK not in shown:  # a user part that redact did not see as one: none of it shows
            shown = f"***@{shown.rpartition('@')[2]}"
        raise MpiLidarError(f"the Dask scheduler address {shown} carries credentials, which Dask "
                            "addresses do not take; give --scheduler tcp://host:port and put TLS certificates in "
                            "Dask's configuration (distributed.comm.tls)")
    return scheduler


@contextmanager
def dask_client(scheduler: str | None = None, workers: int = 2) -> Iterator[Client]:
    """A Dask client for the run.

    Parameters
    ----------
    scheduler : Address of a running scheduler (``tcp://host:8786``); None starts a LocalCluster. An address
        with credentials is refused (:func:`check_scheduler_address`).
    workers : Worker processes of the LocalCluster, one thread each (numpy does the inner parallelism); 0 runs
        one worker thread in this process (for libraries such as ``xgboost.dask`` that need a cluster).
    """
    install_log_redaction()  # Dask and its comms log addresses: their records are masked like every message
    if scheduler:
        check_scheduler_address(scheduler)
        try:
            client = Client(scheduler, timeout=CONNECT_TIMEOUT_S)
        except (OSError, TimeoutError, ValueError) as exc:  # ValueError: an address Dask cannot parse
            problem = ("is not a Dask address" if isinstance(exc, ValueError)
                       else f"cannot be reached ({type(exc).__name__})")
            raise MpiLidarError(
                f"the Dask scheduler at {redact(scheduler)} {problem}; start it with 'dask scheduler' and "
                "'dask worker' and give its tcp://host:port, or leave out --scheduler to use a local cluster"
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
