"""Publishing a batch's outputs: one batch at a time per output location, each output whole or not at all.

A batch (``mpi-lidar correct``, the correction flow) holds its output location for as long as it runs
(:class:`OutputLock`), and publishes each output inside it whole or not at all: built under a staging name and
published at once (:func:`mpi_lidar.storage.atomic.atomic_path`). While it holds the location it may remove
the staging a killed batch left there, since no other batch writes there. :class:`LocalOutputLock` is the
location on a local (or NFSv4) file system; :func:`output_lock` holds a local directory;
:class:`mpi_lidar.storage.objects.ObjectOutputLock` a prefix in an object store, whose outputs are published by
a manifest written last instead of a rename (:func:`mpi_lidar.storage.objects.publish_directory`).
"""

from __future__ import annotations

import fcntl
import os
import socket
import threading
import time
from abc import ABC, abstractmethod
from collections.abc import Iterator
from contextlib import AbstractContextManager, contextmanager
from pathlib import Path, PurePosixPath

from mpi_lidar.errors import MpiLidarError
from mpi_lidar.storage.atomic import remove_interrupted_staging

LOCK_FILE = ".mpi-lidar-correct.lock"  # <out>/: held by the batch writing there (LocalOutputLock)


class OutputLock(ABC):
    """An output location held by one batch at a time.

    Guarantees of every implementation:

    - Exclusive: while :meth:`hold`'s block runs, a second hold of the same location from another process,
      host or thread is refused at once (no waiting) with one :class:`~mpi_lidar.errors.MpiLidarError` line
      that names the holder (process, host, start; never its command line, which may carry a secret).
    - Re-entrant within a thread: nested holds of one location in one thread (a command around a batch and
      its summary) are one hold, released when the outermost ends.
    - Never stale: a holder that dies, even killed, releases the location; whatever it left there does not
      block the next batch.
    - Safe clean-up: only a holder calls :meth:`remove_interrupted`, so no batch's staging in progress is
      removed.

    Not guaranteed: fairness or queueing (a refused batch is not retried), and any hold across a location
    whose storage does not honour the implementation's mechanism (see the implementation).
    """

    @abstractmethod
    def hold(self) -> AbstractContextManager[None]:
        """Hold the location for the block's duration; refused with one line if another batch holds it."""

    @abstractmethod
    def remove_interrupted(self, folder: PurePosixPath) -> None:
        """Remove the staging that an interrupted batch left in ``folder`` (relative to the location), while held."""


class LocalOutputLock(OutputLock):
    """An output directory on a file system, held by an exclusive ``flock`` on ``<out_dir>/`` :data:`LOCK_FILE`.

    The lock file names its holder (process, host, start); the kernel releases the flock when the holder ends,
    even killed, so a lock is never stale. The file is removed when the hold ends (a run that was killed leaves
    it, and the next run takes it over). A batch in another thread of the same process is refused like one in
    another process. Works where the file system supports ``flock`` across its clients (local disks; NFSv4
    on Linux). Each output inside is published by a rename (:func:`~mpi_lidar.storage.atomic.atomic_path`).
    """

    def __init__(self, out_dir: str | Path):
        self.out_dir = Path(out_dir)

    def hold(self) -> AbstractContextManager[None]:
        return _hold(self.out_dir)

    def remove_interrupted(self, folder: PurePosixPath) -> None:
        remove_interrupted_staging(self.out_dir.joinpath(*folder.parts))


def output_lock(out_dir: str | Path) -> AbstractContextManager[None]:
    """Hold the local directory ``out_dir`` for one batch (:class:`LocalOutputLock`)."""
    return LocalOutputLock(out_dir).hold()


_depths: dict[tuple[str, int], int] = {}  # (location, thread) -> depth of nesting, of the holds of this process
_depths_lock = threading.Lock()


@contextmanager
def counted_hold(name: str) -> Iterator[bool]:
    """Count one hold of the location ``name`` by this thread for the block's duration; yields whether it is
    the outermost one, which alone takes and releases the location (the re-entrance every
    :class:`OutputLock` guarantees). Holds by other threads are counted apart, so they are refused."""
    key = (name, threading.get_ident())
    with _depths_lock:
        outermost = key not in _depths
        _depths[key] = _depths.get(key, 0) + 1
    try:
        yield outermost
    finally:
        with _depths_lock:
            _depths[key] -= 1
            if not _depths[key]:
                del _depths[key]


@contextmanager
def _hold(out_dir: Path) -> Iterator[None]:
    """:meth:`LocalOutputLock.hold`: the flock, taken once per thread however deeply the holds nest."""
    with counted_hold(os.path.realpath(out_dir)) as outermost:
        if not outermost:
            yield
            return
        path = out_dir / LOCK_FILE
        descriptor = _take_lock(path, out_dir)
        try:
            yield
        finally:
            try:
                path.unlink(missing_ok=True)  # while still held: a run waiting on this file retries on a fresh one
            finally:
                os.close(descriptor)  # releases the flock


def _take_lock(path: Path, out_dir: Path) -> int:
    """The descriptor of ``path``, exclusively locked and naming this process; refused if another holds it."""
    for _ in range(100):  # the file may be replaced between open and lock (its holder removed it): open again
        try:
            descriptor = os.open(path, os.O_RDWR | os.O_CREAT | getattr(os, "O_NOFOLLOW", 0), 0o644)
        except OSError as exc:
            raise MpiLidarError(f"cannot lock output directory {out_dir} ({path.name}: {exc.strerror or exc}); "
                                "check its permissions or choose another --out") from None
        try:
            fcntl.flock(descriptor, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            holder = _holder(descriptor)
            os.close(descriptor)
            raise MpiLidarError(f"output directory {out_dir} is being written by another correct run ({holder}); "
                                "wait for it to finish or choose another --out") from None
        try:
            same = os.fstat(descriptor).st_ino == os.stat(path, follow_symlinks=False).st_ino
        except OSError:
            same = False
        if same:
            # Who and since when; never its command line, which may carry a secret (a scheduler's password).
            started = time.strftime("%Y-%m-%d %H:%M:%S %Z")
            os.ftruncate(descriptor, 0)
            os.pwrite(descriptor, f"pid {os.getpid()} on {socket.gethostname()}, started {started}\n"
                      .encode(errors="replace"), 0)
            return descriptor
        os.close(descriptor)
    raise MpiLidarError(f"cannot lock output directory {out_dir}: its lock file keeps changing; choose another --out")


def _holder(descriptor: int) -> str:
    """Who holds a lock, as its file says (one line, printable), or that it does not say."""
    try:
        text = os.pread(descriptor, 400, 0).decode(errors="replace").splitlines()
    except OSError:
        text = []
    line = "".join(ch for ch in (text[0] if text else "") if ch.isprintable()).strip()
    return line or "a process that has not yet named itself"
