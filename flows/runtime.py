"""Where flow runs report to and where their tasks run: one Prefect API per run, a Dask task runner, and the
executor through which the library's loops submit the flows' tasks.

Prefect with no ``PREFECT_API_URL`` runs in ephemeral mode: the first API client of a process starts a
temporary server (:class:`~prefect.server.api.server.SubprocessASGIServer`) for that process alone. A Dask
worker is another process, so without care every worker starts a server of its own on the same SQLite file
(slow, and they race on its migrations) and the task runs it records may land on a server nobody reads.

:func:`shared_api` closes that gap. If an API is configured it is used; otherwise it starts (or finds) the
process's default temporary server, the very instance ``prefect.get_client()`` starts in ephemeral mode
(``SubprocessASGIServer()``, keyed by port ``None``), so the flow and its tasks use one server. Its URL then
goes into the current settings, which Prefect serialises into every task it ships to a Dask worker, and into
``os.environ["PREFECT_API_URL"]``, which worker processes spawned from here inherit before they import Prefect.

:class:`PrefectExecutor` is the flows' :class:`~mpi_lidar.workflows.executor.Executor`: the library's loops
(:func:`mpi_lidar.workflows.generate.generate`, :func:`mpi_lidar.workflows.correct_archive.correct_archive`)
run each call as a run of the flow's Prefect task for that library function (its name, run names, retries),
submitted to a :class:`~prefect_dask.DaskTaskRunner`, or run in the flow's process when there is no runner.
"""

from __future__ import annotations

import logging
import os
from collections.abc import Callable, Iterable, Iterator
from contextlib import contextmanager
from typing import Any, Self, TypeVar

from distributed import LocalCluster
from prefect import Task, task
from prefect.cache_policies import NO_CACHE
from prefect.futures import as_completed
from prefect.settings import PREFECT_API_URL, get_current_settings, temporary_settings
from prefect_dask import DaskTaskRunner

from mpi_lidar.errors import MpiLidarError
from mpi_lidar.locations import display_url
from mpi_lidar.workflows.cluster import check_scheduler_address
from mpi_lidar.workflows.executor import Call, Executor

R = TypeVar("R")

API_URL_VARIABLE = "PREFECT_API_URL"


def api_url(startup_timeout_s: int | None = None) -> tuple[str, bool]:
    """The API this process reports to, and whether this call started a temporary server for it.

    ``startup_timeout_s`` None waits ``PREFECT_SERVER_EPHEMERAL_STARTUP_TIMEOUT_SECONDS``.
    """
    configured = get_current_settings().api.url
    if configured:
        return configured, False
    from prefect.server.api.server import SubprocessASGIServer  # 2 s of imports a process with an API never needs

    server = SubprocessASGIServer()  # the process-wide default instance, shared with prefect.get_client()
    started = not server.running
    server.start(timeout=startup_timeout_s)
    return server.api_url, started


@contextmanager
def shared_api(startup_timeout_s: int | None = None, stop_started: bool = False) -> Iterator[str]:
    """This process and every process started inside the block report to one Prefect API; yields its URL.

    ``stop_started`` stops a temporary server this call started when the block ends (for a test session);
    a flow leaves it running, as ephemeral mode does, because the flow run itself still reports to it.
    """
    url, started = api_url(startup_timeout_s)
    previous = os.environ.get(API_URL_VARIABLE)
    os.environ[API_URL_VARIABLE] = url
    try:
        with temporary_settings(updates={PREFECT_API_URL: url}):
            yield url
    finally:
        if previous is None:
            os.environ.pop(API_URL_VARIABLE, None)
        else:
            os.environ[API_URL_VARIABLE] = previous
        if started and stop_started:
            from prefect.server.api.server import SubprocessASGIServer

            SubprocessASGIServer().stop()


def dask_task_runner(workers: int = 2, scheduler: str | None = None) -> DaskTaskRunner:
    """A task runner on the scheduler at ``scheduler``, or on a LocalCluster of ``workers`` processes.

    One thread per worker process, as in :func:`mpi_lidar.workflows.cluster.dask_client`: numpy does the inner work.
    The cluster starts when the first task is submitted, not here.
    """
    if scheduler:
        return DaskTaskRunner(address=check_scheduler_address(scheduler))
    if workers < 1:
        raise MpiLidarError(f"workers must be at least 1, got {workers}")
    return DaskTaskRunner(cluster_class=LocalCluster, cluster_kwargs=local_cluster_kwargs(workers))


def local_cluster_kwargs(workers: int) -> dict[str, object]:
    """A quiet LocalCluster of ``workers`` processes x 1 thread, with no dashboard.

    ``dashboard_address=None`` alone leaves the scheduler's HTTP routes (health, metrics) on port 8787, and a
    warning when another cluster holds it; they go on a free port instead, still without the dashboard.
    """
    return {"n_workers": workers, "threads_per_worker": 1, "processes": True, "dashboard_address": None,
            "scheduler_kwargs": {"dashboard": False, "dashboard_address": "127.0.0.1:0"},
            "silence_logs": logging.ERROR}


def describe_workers(workers: int, scheduler: str | None) -> str:
    """How the chunks ran, for reports (no workers: in the flow's process, as ``mpi-lidar simulate --workers 0``)."""
    if workers == 0:
        return "the flow's process"
    if scheduler:
        return f"Dask scheduler {display_url(scheduler)}"
    return f"LocalCluster, {workers} process{'es' * (workers != 1)} x 1 thread"


class PrefectExecutor(Executor):
    """Each call of a library loop as a run of a Prefect task, on a Dask task runner or in the flow's process.

    ``tasks`` are the flow's tasks made from the library functions themselves (``task(dataset.write_chunk,
    name="write-chunk", ...)``): a call of ``fn`` runs the task whose ``fn`` it is, so the flow sets the task's
    name, run names and retries. A function without a task gets a plain one named after it, retried
    ``retries`` times. Entering the executor starts the runner's cluster (or connects to its scheduler), and
    leaving it shuts down what it started; without a runner the calls run one after the other in this
    process, still as task runs of the flow.
    """

    def __init__(self, runner: DaskTaskRunner | None, tasks: Iterable[Task[..., Any]] = ()) -> None:
        self.runner = runner
        self.tasks = {t.fn: t for t in tasks}

    def __enter__(self) -> Self:
        if self.runner is not None:
            self.runner.__enter__()
            _ = self.runner.client  # start the cluster (or connect to the scheduler) now, not in the first map
        return self

    def __exit__(self, *exc_info: object) -> None:
        if self.runner is not None:
            self.runner.__exit__(*exc_info)

    def task_for(self, fn: Callable[..., R], retries: int = 0) -> Task[..., R]:
        found = self.tasks.get(fn)
        if found is None:
            name = getattr(fn, "__name__", "call").replace("_", "-")
            found = self.tasks[fn] = task(fn, name=name, cache_policy=NO_CACHE, retries=retries)
        return found

    def map(self, fn: Callable[..., R], calls: Iterable[Call], *, retries: int = 0) -> Iterator[tuple[Call, R]]:
        run = self.task_for(fn, retries)
        if self.runner is None:
            for call in calls:
                yield call, run(**call)
            return
        futures = {self.runner.submit(run, dict(call)): call for call in calls}
        for future in as_completed(list(futures)):
            yield futures[future], future.result()
