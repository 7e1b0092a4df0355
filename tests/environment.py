"""Environment variables set for a block and put back after it, for the servers the object-store tests start."""

from __future__ import annotations

import os
from collections.abc import Callable, Iterable, Iterator
from contextlib import contextmanager


@contextmanager
def environment(names: Iterable[str], values: dict[str, str], forget: Callable[[], None]) -> Iterator[None]:
    """Inside: the variables ``names`` unset but for ``values`` (processes started inside inherit them); ``forget``
    called on entering and on leaving, as a store library's cached clients read the variables when they were made.
    Every variable of ``names`` and ``values`` is as it was after the block."""
    saved = {name: os.environ.get(name) for name in {*names, *values}}
    for name in saved:
        os.environ.pop(name, None)
    os.environ.update(values)
    forget()
    try:
        yield
    finally:
        for name, value in saved.items():
            if value is None:
                os.environ.pop(name, None)
            else:
                os.environ[name] = value
        forget()
