"""Work on every core of this process: for independent pieces whose heavy loops release the GIL (NumPy,
hashlib, zarr's decoding)."""

from __future__ import annotations

import os
from collections.abc import Callable, Iterable
from concurrent.futures import ThreadPoolExecutor
from typing import TypeVar

T = TypeVar("T")
R = TypeVar("R")


def on_cores(work: Callable[[T], R], items: Iterable[T]) -> list[R]:
    """``work`` of each item, results in the items' order, on one thread per core (here, for one item or one
    core). An exception is that of the first item, in order, that raised one."""
    items = list(items)
    workers = min(len(items), os.cpu_count() or 1)
    if workers <= 1:
        return [work(item) for item in items]
    with ThreadPoolExecutor(workers) as pool:
        return list(pool.map(work, items))
