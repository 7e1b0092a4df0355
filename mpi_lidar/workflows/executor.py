"""Where the items of a loop run: in this process, as tasks on a Dask client, or as the flows' Prefect tasks.

The loops of the workflows (a dataset chunk by chunk, an archive scan by scan) are written once, against
:class:`Executor`: ``executor.map(fn, calls)`` runs ``fn(**call)`` for every call and yields each call with
its result as it finishes. :class:`InProcess` runs them one after the other here, :class:`DaskExecutor` submits
one Dask task per call; the Prefect flows plug in their own (``flows.runtime.PrefectExecutor``), which runs
each call as a Prefect task on a Dask task runner. Calls are keyword arguments, so an orchestrator can name
its task runs after them (``write-chunk-{index}``).

An executor is a context manager: entering it starts what it needs (its workers), so the loops' clocks time
the work and not the start-up, and leaving it releases what it started. Dask is imported only by what uses
it, so a loop run in this process does not pay for importing ``distributed``.
"""

from __future__ import annotations

import uuid
from abc import ABC, abstractmethod
from collections.abc import Callable, Iterable, Iterator, Mapping
from contextlib import contextmanager
from typing import TYPE_CHECKING, Any, Self, TypeVar

if TYPE_CHECKING:
    from distributed import Client

R = TypeVar("R")
Call = Mapping[str, Any]  # the keyword arguments of one call


class Executor(ABC):
    """Runs the calls of a loop and yields their results as they complete."""

    @abstractmethod
    def map(self, fn: Callable[..., R], calls: Iterable[Call], *, retries: int = 0) -> Iterator[tuple[Call, R]]:
        """``(call, fn(**call))`` for every call, in the order they finish.

        ``retries`` is how often a call that raised may be run again where failures can come from the
        infrastructure (a lost worker); ``fn`` must be safe to rerun. An exception of the last try is raised
        from the iterator.
        """

    def __enter__(self) -> Self:
        return self

    def __exit__(self, *exc_info: object) -> None:
        return None


class InProcess(Executor):
    """Every call in this process, one after the other; an exception is the caller's, so nothing is retried."""

    def map(self, fn: Callable[..., R], calls: Iterable[Call], *, retries: int = 0) -> Iterator[tuple[Call, R]]:
        for call in calls:
            yield call, fn(**call)


def _apply(fn: Callable[..., R], call: Call) -> R:
    return fn(**call)


class DaskExecutor(Executor):
    """One task per call on a Dask client; nothing but the results comes back to the client."""

    def __init__(self, client: Client) -> None:
        self.client = client

    def map(self, fn: Callable[..., R], calls: Iterable[Call], *, retries: int = 0) -> Iterator[tuple[Call, R]]:
        from distributed import as_completed

        name = getattr(fn, "__name__", "call").replace("_", "-")
        futures = {self.client.submit(_apply, fn, call, key=f"{name}-{uuid.uuid4().hex}", retries=retries,
                                      pure=False): call
                   for call in calls}
        for future in as_completed(futures):
            yield futures[future], future.result()


def as_executor(where: Executor | Client | None) -> Executor:
    """An executor for ``where``: itself, a Dask client's tasks, or (None) this process."""
    if where is None:
        return InProcess()
    if isinstance(where, Executor):
        return where
    from distributed import Client

    return DaskExecutor(where) if isinstance(where, Client) else where


@contextmanager
def dask_executor(scheduler: str | None = None, workers: int = 2) -> Iterator[DaskExecutor]:
    """Tasks on the scheduler at ``scheduler``, or on a LocalCluster of ``workers`` processes started here."""
    from mpi_lidar.workflows.cluster import dask_client

    with dask_client(scheduler, workers) as client:
        yield DaskExecutor(client)
