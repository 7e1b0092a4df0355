"""Bounded reads of the small text files a user names: configurations, sensor profiles, parameter files.

:func:`read_small_text` reads only a regular file (a symbolic link is followed to one), of at most
:data:`MAX_CONFIG_BYTES`, as UTF-8. A FIFO, a device (``/dev/zero``, ``/dev/stdin``), a socket or a directory is
refused before a byte is read, and so is a larger file: its size is checked before the read, and the read
itself stops one byte past the limit, so a file that grows meanwhile is refused too. The file is opened
non-blocking, so a FIFO swapped in between the check and the open cannot hang the process either.
Every refusal is one line naming the file and what to do (:class:`mpi_lidar.errors.ConfigError`).
"""

from __future__ import annotations

import errno
import os
import stat
from pathlib import Path

from mpi_lidar.errors import ConfigError

MAX_CONFIG_BYTES = 1 << 20  # 1 MiB: a configuration, a sensor profile or a parameter file is a few kilobytes


def _kind(mode: int) -> str:
    for test, name in ((stat.S_ISDIR, "a directory"), (stat.S_ISFIFO, "a FIFO (named pipe)"),
                       (stat.S_ISCHR, "a character device"), (stat.S_ISBLK, "a block device"),
                       (stat.S_ISSOCK, "a socket")):
        if test(mode):
            return name
    return "not a regular file"


def regular_file_size(path: str | Path, what: str, limit: int | None = None) -> int:
    """The size [bytes] of ``path`` if it is a regular file (a symbolic link is followed) of at most ``limit``
    bytes (None: any size); otherwise :class:`ConfigError`, one line. Nothing is opened: a reader of a larger
    file (a scan import) calls this before it opens ``path``, so a FIFO or a device never reaches it."""
    path = Path(path)
    try:
        info = path.stat()
    except FileNotFoundError:
        raise ConfigError(f"{what} {path} does not exist; check the path") from None
    except OSError as exc:
        raise ConfigError(f"{what} {path} cannot be read: {exc.strerror or exc}; check its permissions") from None
    if stat.S_ISDIR(info.st_mode):
        raise ConfigError(f"{what} {path} is a directory; give the path of a file")
    if not stat.S_ISREG(info.st_mode):
        raise ConfigError(f"{what} {path} is {_kind(info.st_mode)}, not a regular file; give the path of a file")
    if limit is not None and info.st_size > limit:
        raise ConfigError(f"{what} {path} holds {info.st_size:,} bytes, more than the {limit:,} a {what} may "
                          "have; check that it is the right file")
    return info.st_size


def read_small_bytes(path: str | Path, what: str, limit: int = MAX_CONFIG_BYTES) -> bytes:
    """The bytes of the regular file ``path`` (``what`` names it in errors, e.g. "config file"), at most ``limit``.

    Raises :class:`ConfigError` (one line) for a missing or unreadable file, anything but a regular file, and a
    file larger than ``limit`` bytes.
    """
    path = Path(path)
    regular_file_size(path, what, limit)  # refused before it is opened: opening a device can act by itself
    try:
        # O_NONBLOCK: opening a FIFO without a writer returns at once instead of waiting for one.
        fd = os.open(path, os.O_RDONLY | os.O_NONBLOCK | getattr(os, "O_CLOEXEC", 0))
    except FileNotFoundError:
        raise ConfigError(f"{what} {path} does not exist; check the path") from None
    except IsADirectoryError:
        raise ConfigError(f"{what} {path} is a directory; give the path of a file") from None
    except OSError as exc:
        if exc.errno == errno.ENXIO:  # a socket, or a FIFO on a system that refuses a non-blocking open
            raise ConfigError(f"{what} {path} is not a regular file; give the path of a file") from None
        raise ConfigError(f"{what} {path} cannot be read: {exc.strerror or exc}; check its permissions") from None
    try:
        info = os.fstat(fd)
        if not stat.S_ISREG(info.st_mode):
            raise ConfigError(f"{what} {path} is {_kind(info.st_mode)}, not a regular file; give the path of a "
                              "file")
        if info.st_size > limit:
            raise ConfigError(f"{what} {path} holds {info.st_size:,} bytes, more than the {limit:,} a {what} may "
                              "have; check that it is the right file")
        chunks: list[bytes] = []
        size = 0
        while size <= limit:
            chunk = os.read(fd, min(limit + 1 - size, 1 << 16))
            if not chunk:
                break
            chunks.append(chunk)
            size += len(chunk)
        if size > limit:
            raise ConfigError(f"{what} {path} grew past the {limit:,} bytes a {what} may have while it was read; "
                              "check that it is the right file")
        return b"".join(chunks)
    except OSError as exc:
        raise ConfigError(f"{what} {path} cannot be read: {exc.strerror or exc}") from None
    finally:
        os.close(fd)


def read_small_text(path: str | Path, what: str, limit: int = MAX_CONFIG_BYTES, kind: str = "UTF-8 text") -> str:
    """:func:`read_small_bytes` decoded as UTF-8; a file that is not UTF-8 is refused with its byte offset, as not
    valid ``kind`` (e.g. "TOML")."""
    data = read_small_bytes(path, what, limit)
    try:
        return data.decode("utf-8")
    except UnicodeDecodeError as exc:
        raise ConfigError(f"{what} {path} is not valid {kind}: byte {exc.start} ({data[exc.start:exc.start + 1]!r}) "
                          "is not UTF-8; save it as UTF-8") from None
