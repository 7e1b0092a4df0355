"""Generate a dataset store chunk by chunk, resuming an interrupted one, on any executor.

The store and its chunks are :mod:`mpi_lidar.simulation.dataset`'s; here is the loop: one call of
:func:`~mpi_lidar.simulation.dataset.write_chunk` per incomplete chunk, in this process, as Dask tasks or as
the Prefect flow's tasks (:mod:`mpi_lidar.workflows.executor`). A chunk's bytes do not depend on where or in
which order it is written, so every executor writes the same store.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path

from distributed import Client

from mpi_lidar.config import Config
from mpi_lidar.errors import StoreError
from mpi_lidar.simulation import dataset
from mpi_lidar.workflows.executor import Executor, as_executor

CHUNK_RETRIES = 2  # a chunk task lost with its worker, or failing on the infrastructure, runs again


@dataclass(frozen=True)
class GenerationReport:
    """What one generation run did."""

    chunks_written: int
    chunks_skipped: int
    rows_written: int
    wall_s: float

    @property
    def rows_per_s(self) -> float:
        return self.rows_written / self.wall_s if self.wall_s > 0 else 0.0


def generate(
    path: str | Path,
    config: Config,
    executor: Executor | Client | None = None,
    on_chunk: Callable[[int], None] | None = None,
) -> GenerationReport:
    """Generate the dataset, resuming an interrupted store; one call per incomplete chunk.

    On a Dask executor (or ``client``) each chunk is a task that writes straight into its own region of the
    store (nothing is gathered on the client; a failed task is retried, and a lost worker's tasks are rerun
    by the scheduler). Without one, the chunks run in this process. All write identical bytes. The executor
    is started by the caller, so ``wall_s`` times the store and the chunks, not the start of workers.
    """
    started = time.perf_counter()
    group = dataset.create_store(path, config)
    plan = dataset.SamplingPlan.from_config(config)
    todo = dataset.incomplete_chunks(group)
    try:
        for index in _run_chunks(str(path), config, todo, as_executor(executor)):
            if on_chunk is not None:
                on_chunk(index)
    except OSError as exc:
        raise StoreError(f"writing dataset {path} failed: {exc.strerror or exc}; free space or fix "
                         "permissions, then run again: finished chunks are kept and skipped") from None
    return GenerationReport(len(todo), plan.chunks - len(todo), plan.rows_in(todo), time.perf_counter() - started)


def _run_chunks(path: str, config: Config, todo: list[int], executor: Executor) -> Iterator[int]:
    """The index of every chunk of ``todo`` once it is written, in the order they finish."""
    calls = [{"path": path, "config": config, "index": index} for index in todo]
    for call, _written in executor.map(dataset.write_chunk, calls, retries=CHUNK_RETRIES):
        yield call["index"]
