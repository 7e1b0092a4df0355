"""Atomic writes: every file, directory or store the project writes appears whole or not at all.

Crash-safety contract of :func:`atomic_path` (the one way this project writes an output):

- The output is built under a staging name beside the target, ``.<name>.writing-<8 hex>``, in the same
  directory (so the final rename never crosses a file system).
- Only a block that ends without an exception publishes it. A file or link replaces the target with one
  ``os.replace`` (readers see the old or the new one, never neither). A directory is renamed into place;
  where one already stands and ``replace`` is set, the old one is first renamed to ``.<name>.old-<8 hex>``
  and deleted only after the new one is in place, so a crash in between leaves the old outputs under their
  retired name, never a half-written target.
- An exception, a crash or a kill leaves the target as it was; the staging (and a retired) path left by a
  killed process is recognised by :data:`STAGING_NAME` and removed by :func:`remove_interrupted_staging`.
- Nothing is overwritten unless ``replace`` is set; then ``keep`` may refuse a target that is not ours.
- A directory whose staging holds an empty output marker (``.mpi-lidar-report``) gets the manifest of its files
  written into that marker before it is published (:mod:`mpi_lidar.storage.manifest`), so the manifest
  appears together with the files it lists.
- ``OSError`` (no space, no permission) becomes one :class:`~mpi_lidar.errors.MpiLidarError` line naming
  the target.

Not guaranteed: durability across a power loss (no fsync), and two writers of the same target at once
(the last rename wins).
"""

from __future__ import annotations

import os
import re
import shutil
import uuid
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path

from mpi_lidar.errors import MpiLidarError

STAGING_NAME = re.compile(r"^\..+\.(writing|old)-[0-9a-f]{8}$")


def _sibling(target: Path, role: str) -> Path:
    return target.parent / f".{target.name}.{role}-{uuid.uuid4().hex[:8]}"


def _remove(path: Path) -> None:
    if path.is_symlink() or path.is_file():
        path.unlink(missing_ok=True)
    elif path.exists():
        shutil.rmtree(path, ignore_errors=True)


@contextmanager
def atomic_path(target: str | Path, *, replace: bool = False, what: str = "output",
                keep: Callable[[Path], bool] | None = None,
                error: type[MpiLidarError] = MpiLidarError) -> Iterator[Path]:
    """Yield a staging path for ``target``; publish it atomically when the block ends without an exception.

    Parameters
    ----------
    target : The file, directory or store to write.
    replace : Replace an existing target (otherwise an existing target is refused before any work).
    what : What the target is, for the error line (``"model directory"``, ``"scan"``...).
    keep : Called with an existing target when ``replace`` is set; True refuses to replace it (not ours).
    error : The exception type of the one-line errors (a subclass of MpiLidarError).
    """
    target = Path(target)
    if target.exists() or target.is_symlink():
        if not replace:
            raise error(f"{what} {target} already exists; choose another name or remove it")
        if keep is not None and keep(target):
            raise error(f"{target} exists and is not an mpi-lidar {what}; choose another path")
    staging = _sibling(target, "writing")
    try:
        target.parent.mkdir(parents=True, exist_ok=True)
        yield staging
        if staging.is_dir() and not staging.is_symlink():
            # here, not at import: writing a file keeps this module free of numpy and zarr
            from mpi_lidar.storage.manifest import unsealed, write_manifest

            if unsealed(staging):
                write_manifest(staging)  # the outputs' manifest, published with them
        _publish(staging, target)
    except MpiLidarError:  # already one line (a StoreError is also an OSError): not a failed write
        raise
    except OSError as exc:
        raise error(f"cannot write {what} {target}: {exc.strerror or exc}; choose a writable path "
                            "with free space") from None
    finally:
        _remove(staging)


def _publish(staging: Path, target: Path) -> None:
    if not staging.is_dir() or staging.is_symlink() or not target.is_dir() or target.is_symlink():
        os.replace(staging, target)
        return
    retired = _sibling(target, "old")
    os.replace(target, retired)
    os.replace(staging, target)
    _remove(retired)


def write_bytes(target: str | Path, data: bytes, *, what: str = "file") -> Path:
    """Write ``data`` to ``target`` through :func:`atomic_path`, replacing a previous file."""
    with atomic_path(target, replace=True, what=what) as staging:
        staging.write_bytes(data)
    return Path(target)


def write_text(target: str | Path, text: str, *, what: str = "file") -> Path:
    """Write ``text`` (UTF-8) to ``target`` through :func:`atomic_path`, replacing a previous file."""
    return write_bytes(target, text.encode(), what=what)


def remove_interrupted_staging(directory: str | Path) -> list[Path]:
    """Delete the staging and retired paths a killed writer left in ``directory``; they are never outputs.

    Call it before a batch starts writing there: a writer running at the same time into the same directory
    could lose its staging to it, and that is not supported.
    """
    directory = Path(directory)
    if not directory.is_dir():
        return []
    leftovers = [p for p in directory.iterdir() if STAGING_NAME.match(p.name)]
    for path in leftovers:
        _remove(path)
    return leftovers
