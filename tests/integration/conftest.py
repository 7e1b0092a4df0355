"""A real multi-process Dask cluster and fresh PostgreSQL databases for the integration tests.

The cluster is what users start by hand: one ``dask scheduler`` and ``dask worker`` processes on 127.0.0.1,
each in its own process group so a test can kill one worker and teardown can kill them all. Databases are
created under a unique name on the local PostgreSQL server and dropped with their connections afterwards.
"""

from __future__ import annotations

import contextlib
import os
import signal
import socket
import subprocess
import sys
import time
import uuid
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path

import pytest

from tests.conftest import mark_directory

REPO = Path(__file__).resolve().parents[2]
BIN = Path(sys.executable).parent
POSTGRES_ADMIN_URL = os.environ.get("MPI_LIDAR_TEST_POSTGRES", "postgresql://postgres@127.0.0.1:5432/postgres")
START_TIMEOUT_S = 60


@pytest.hookimpl(tryfirst=True)
def pytest_collection_modifyitems(items: list[pytest.Item]) -> None:
    """Every test in this directory is an integration test (tests/conftest.py)."""
    mark_directory(items, Path(__file__).resolve().parent, "integration")


def free_port() -> int:
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        return probe.getsockname()[1]


def subprocess_env(**extra: str) -> dict[str, str]:
    """The environment of every process the tests start: the repository importable, quiet Dask logs."""
    env = {**os.environ, "PYTHONPATH": str(REPO), "DASK_LOGGING__DISTRIBUTED": "error"}
    env.pop("PREFECT_API_URL", None)
    return {**env, **extra}


def stop_group(process: subprocess.Popen, sig: int = signal.SIGKILL) -> None:
    """Kill a process we started and everything in its process group, then reap it."""
    if process.poll() is None:
        with contextlib.suppress(ProcessLookupError):
            os.killpg(process.pid, sig)
    try:
        process.wait(timeout=20)
    except subprocess.TimeoutExpired:
        os.killpg(process.pid, signal.SIGKILL)
        process.wait(timeout=20)


@dataclass
class DaskCluster:
    """A scheduler and worker processes started with the ``dask`` command line."""

    address: str
    log_dir: Path
    scheduler: subprocess.Popen
    workers: list[subprocess.Popen] = field(default_factory=list)

    def add_worker(self) -> subprocess.Popen:
        log = (self.log_dir / f"worker-{len(self.workers)}.log").open("w")
        process = subprocess.Popen(
            [str(BIN / "dask"), "worker", self.address, "--nworkers", "1", "--nthreads", "1", "--no-dashboard",
             "--host", "127.0.0.1", "--death-timeout", "60"],
            stdout=log, stderr=subprocess.STDOUT, env=subprocess_env(), cwd=REPO, start_new_session=True)
        self.workers.append(process)
        return process

    def wait_for_workers(self, n: int) -> None:
        from distributed import Client

        with Client(self.address, timeout=START_TIMEOUT_S) as client:
            client.wait_for_workers(n, timeout=START_TIMEOUT_S)

    def stop(self) -> None:
        for process in [*self.workers, self.scheduler]:
            stop_group(process)


def start_cluster(log_dir: Path, workers: int = 2) -> DaskCluster:
    port = free_port()
    log = (log_dir / "scheduler.log").open("w")
    scheduler = subprocess.Popen(
        [str(BIN / "dask"), "scheduler", "--host", "127.0.0.1", "--port", str(port), "--no-dashboard"],
        stdout=log, stderr=subprocess.STDOUT, env=subprocess_env(), cwd=REPO, start_new_session=True)
    cluster = DaskCluster(f"tcp://127.0.0.1:{port}", log_dir, scheduler)
    try:
        deadline = time.monotonic() + START_TIMEOUT_S
        while True:
            try:
                socket.create_connection(("127.0.0.1", port), timeout=1).close()
                break
            except OSError:
                if scheduler.poll() is not None or time.monotonic() > deadline:
                    log_text = (log_dir / "scheduler.log").read_text()
                    raise RuntimeError(f"dask scheduler did not start: {log_text}") from None
                time.sleep(0.2)
        for _ in range(workers):
            cluster.add_worker()
        cluster.wait_for_workers(workers)
    except BaseException:
        cluster.stop()
        raise
    return cluster


@pytest.fixture(scope="session")
def dask_cluster(tmp_path_factory: pytest.TempPathFactory) -> Iterator[DaskCluster]:
    """``dask scheduler`` plus two ``dask worker`` processes (one process, one thread each) on 127.0.0.1.

    A test may kill a worker process: its nanny starts a new one, as in production. Such a test waits for
    two workers again before it ends, so the next test finds the cluster whole.
    """
    cluster = start_cluster(tmp_path_factory.mktemp("dask-logs"), workers=2)
    try:
        yield cluster
    finally:
        cluster.stop()


@pytest.fixture(scope="session")
def cluster_model(tmp_path_factory: pytest.TempPathFactory, dask_cluster: DaskCluster, small_dataset: Path) -> Path:
    """A small residual model trained through xgboost.dask on the process cluster."""
    from distributed import Client

    from mpi_lidar.config import Config
    from mpi_lidar.learning.features import FeatureSpec
    from mpi_lidar.learning.train import train_and_save

    params = {"max_depth": 4, "learning_rate": 0.3}
    with Client(dask_cluster.address, timeout=START_TIMEOUT_S) as client:
        out, _ = train_and_save(client, small_dataset, tmp_path_factory.mktemp("model") / "model",
                                FeatureSpec(Config().frequencies_hz, "raw", "residual"), params,
                                num_boost_round=40, early_stopping_rounds=5)
    return out


def database_url(name: str, password: str | None = None) -> str:
    base = POSTGRES_ADMIN_URL.rsplit("/", 1)[0]
    if password:
        base = base.replace("://postgres@", f"://postgres:{password}@", 1)
    return f"{base}/{name}"


@pytest.fixture
def pg_database() -> Iterator[str]:
    """The name of a fresh, uniquely named PostgreSQL database, dropped (with its connections) afterwards."""
    import psycopg

    name = f"mpi_lidar_it_{uuid.uuid4().hex[:10]}"
    with psycopg.connect(POSTGRES_ADMIN_URL, autocommit=True) as admin:
        admin.execute(f'CREATE DATABASE "{name}"')
    try:
        yield name
    finally:
        with psycopg.connect(POSTGRES_ADMIN_URL, autocommit=True) as admin:
            admin.execute(f'DROP DATABASE IF EXISTS "{name}" WITH (FORCE)')


def terminate_connections(database: str) -> int:
    """Terminate every server connection to ``database`` (what a PostgreSQL restart or failover does to them)."""
    import psycopg

    with psycopg.connect(POSTGRES_ADMIN_URL, autocommit=True) as admin:
        rows = admin.execute("SELECT pg_terminate_backend(pid) FROM pg_stat_activity "
                             "WHERE datname = %s AND pid <> pg_backend_pid()", (database,)).fetchall()
    return len(rows)


def run_cli(*args: str, env: dict[str, str] | None = None, timeout: float = 600,
            check: bool = True) -> subprocess.CompletedProcess[str]:
    """Run ``mpi-lidar`` as users do, in a process of its own."""
    result = subprocess.run([str(BIN / "mpi-lidar"), *args], capture_output=True, text=True, timeout=timeout,
                            env=env or subprocess_env(), cwd=REPO)
    if check and result.returncode != 0:
        raise AssertionError(f"mpi-lidar {' '.join(args)} exited {result.returncode}:\n{result.stderr[-3000:]}")
    return result
