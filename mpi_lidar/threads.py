"""Work on every core of this process: for independent pieces whose heavy loops release the GIL (NumPy,
hashlib, zarr's decoding)."""

from __future__ import annotations

import itertools
import os
from collections.abc import Callable, Iterable
from concurrent.futures import ThreadPoolExecutor
from typing import TypeVar

T = TypeVar("T")
R = TypeVar("R")


def cores() -> int:
    """Threads this process gives to one piece of work: one per core, or fewer where ``OMP_NUM_THREADS`` says
    so. Dask sets it to 1 in its worker processes, which already share the cores among themselves, so a
    worker's scan does not start a thread per core on top of every other worker's."""
    count = os.cpu_count() or 1
    try:
        budget = int(os.environ.get("OMP_NUM_THREADS", ""))
    except ValueError:  # unset, or not a number: no budget
        return count
    return max(1, min(count, budget))


def on_cores(work: Callable[[T], R], items: Iterable[T]) -> list[R]:
    """``work`` of each item, results in the items' order, on one thread per core (:func:`cores`; here, for
    one item or one core). An exception is that of the first item, in order, that raised one."""
    items = list(items)
    workers = min(len(items), cores())
    if workers <= 1:
        return [work(item) for item in items]
    with ThreadPoolExecutor(workers) as pool:
        return list(pool.map(work, items))


def on_cores_by_rows(work: Callable[[slice], R], rows: int, min_rows: int) -> list[R]:
    """``work`` on consecutive row ranges that together cover ``rows``, one range per core (:func:`on_cores`),
    each at least ``min_rows`` long (one range alone for fewer rows); results in row order."""
    parts = max(1, min(cores(), rows // min_rows))
    bounds = [rows * k // parts for k in range(parts + 1)]
    return on_cores(work, [slice(a, b) for a, b in itertools.pairwise(bounds)])
