"""The exception types the CLI turns into a single error line, and the exit codes.

Each also derives from the built-in exception a caller would catch for the same trouble, so code that knows
nothing of this package still handles it: a store that cannot be read is an :class:`OSError`, a configuration
that cannot be used a :class:`ValueError`. Every ``except OSError`` / ``except ValueError`` of the package
around a call that raises these either re-raises them first or wants them.
"""

from __future__ import annotations

import errno
import os
import stat
import tempfile
from collections.abc import Iterator
from pathlib import Path

EXIT_USER_ERROR = 2  # the exit code of a user error, for the command line and python -m flows.deploy
EXIT_FAILURE = 1  # something failed that is not the input's fault (a scan of a batch, a damaged store, a bug)


class MpiLidarError(Exception):
    """A user-facing error: the message says what was wrong, where, and what to do."""


class ConfigError(MpiLidarError, ValueError):
    """A configuration file or value that cannot be used."""


class StoreError(MpiLidarError, OSError):
    """A dataset or scan store that is missing, foreign, truncated or from another configuration."""


class EnvironmentFaultError(MpiLidarError, OSError):
    """The machine, not the input, stopped the command: a full disk, a quota, a read-only file system."""


# The faults of the environment that are the user's to fix, each with what to do; a user error (exit 2).
_FAULTS = {
    errno.ENOSPC: ("the disk is full", "free space on that disk or write the outputs to another one"),
    errno.EDQUOT: ("the disk quota is exhausted", "free space within the quota or write the outputs to another disk"),
    errno.EROFS: ("the file system is read-only", "write to a writable directory"),
}


# Libraries that report a short write without its errno: XGBoost's model writer (dmlc-core's FileStream).
# A write cut short is what a full disk does to them.
_SHORT_WRITES = ("FileStream.Write incomplete",)


def _chain(exc: BaseException) -> Iterator[BaseException]:
    """``exc``, its causes and contexts, and the members of exception groups, each once."""
    seen: set[int] = set()
    pending = [exc]
    while pending:
        current = pending.pop()
        if id(current) in seen:
            continue
        seen.add(id(current))
        yield current
        pending += [e for e in (current.__cause__, current.__context__) if e is not None]
        if isinstance(current, BaseExceptionGroup):
            pending += list(current.exceptions)


def environment_fault(exc: BaseException) -> EnvironmentFaultError | None:
    """The one-line error of a full disk (``ENOSPC``), an exhausted quota (``EDQUOT``) or a read-only file system
    (``EROFS``) that ``exc`` is or was raised from, or None.

    An :class:`OSError` with that errno is found anywhere in the chain of causes; a library that reports the
    fault only in its message (its strerror, "No space left on device", or XGBoost's "FileStream.Write
    incomplete", a write cut short) is recognised by the message. The line names the file where the OSError
    names one.
    """
    for current in _chain(exc):
        code = current.errno if isinstance(current, OSError) else None
        what = ""
        if code not in _FAULTS:
            text = str(current)
            code = next((c for c in _FAULTS if os.strerror(c) in text), None)
            short = next((s for s in _SHORT_WRITES if s in text), None)
            if code is None and short is None:
                continue
            if code is None:
                code, what = errno.ENOSPC, f"a write was cut short ({short}), as on a full disk"
        what, fix = what or _FAULTS[code][0], _FAULTS[code][1]
        filename = getattr(current, "filename", None) if isinstance(current, OSError) else None
        where = f" writing {os.fsdecode(filename)!r}" if filename not in (None, "") else ""
        fault = EnvironmentFaultError(f"{what} ({errno.errorcode[code]}){where}; {fix}, then run the command again")
        fault.errno = code
        return fault
    return None


def write_error_log(text: str) -> Path | None:
    """Write ``text`` (a traceback, secrets already masked) to this user's error log in the temporary folder.

    The folder is created readable by this user only (0700) and the file 0600; where it cannot be written (a
    full disk, a foreign folder of that name) nothing is raised: the log's path, or None.
    """
    folder = Path(tempfile.gettempdir()) / f"mpi-lidar-{os.getuid()}"
    try:
        folder.mkdir(mode=0o700, exist_ok=True)
        info = folder.lstat()
        if not stat.S_ISDIR(info.st_mode) or info.st_uid != os.getuid():
            return None  # another user's folder, or a link planted in a shared /tmp: write nothing there
        if stat.S_IMODE(info.st_mode) & 0o077:  # made readable to others by an older version: this user's only
            folder.chmod(0o700)
        log = folder / "last-error.log"
        fd = os.open(log, os.O_WRONLY | os.O_CREAT | os.O_TRUNC | os.O_NOFOLLOW, 0o600)
    except OSError:
        return None
    try:
        with os.fdopen(fd, "w", encoding="utf-8", errors="backslashreplace") as handle:
            handle.write(text)
    except OSError:
        log.unlink(missing_ok=True)  # half a traceback would mislead
        return None
    return log
