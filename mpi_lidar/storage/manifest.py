"""The manifest of a scan's output directory: the size and SHA-256 of every file in it, written with them.

A re-run of ``mpi-lidar correct`` skips a scan only if its outputs are what was written: every file the
manifest lists (``corrected.zarr``'s metadata and chunk files, ``metrics.json``, the report, images and point
clouds) is still a regular file of that size and digest (:func:`verify_manifest`). A file deleted, edited,
truncated or replaced by a link fails, and the scan is corrected again.

The manifest is the JSON content of the directory's marker file :data:`MANIFEST_FILE` (the file whose presence
says the directory holds mpi-lidar outputs, ``mpi_lidar.reporting.report.REPORT_MARKER``). A directory
published by :func:`mpi_lidar.storage.atomic.atomic_path` with an empty marker gets its manifest written in
its staging directory, just before the rename: the manifest appears together with the files it lists. An empty
marker (outputs of a version before manifests) lists nothing: such outputs are never skipped. Files added to
the directory afterwards are not listed and not checked.
"""

from __future__ import annotations

import hashlib
import json
import os
import stat
import uuid
from pathlib import Path

from mpi_lidar.storage.integrity import HEX_FINGERPRINT, MAX_METADATA_BYTES, IntegrityError, check_store_files
from mpi_lidar.threads import on_cores

MANIFEST_FILE = ".mpi-lidar-report"
MANIFEST_SCHEMA = "mpi-lidar/outputs-manifest@1"
_READ_BYTES = 2**20


def file_sha256(path: Path) -> str:
    """SHA-256 of a regular file's bytes, read in blocks (a link or special file is refused, not followed)."""
    digest = hashlib.sha256()
    flags = os.O_RDONLY | getattr(os, "O_NOFOLLOW", 0) | getattr(os, "O_NONBLOCK", 0)
    descriptor = os.open(path, flags)
    with os.fdopen(descriptor, "rb") as file:
        if not stat.S_ISREG(os.fstat(file.fileno()).st_mode):
            raise IntegrityError(f"{path} is not a regular file; restore it or correct the scan again")
        while block := file.read(_READ_BYTES):
            digest.update(block)
    return digest.hexdigest()


def write_manifest(directory: str | Path) -> dict[str, dict[str, object]]:
    """List every file under ``directory`` (but the manifest) with its size and SHA-256, into the manifest."""
    directory = Path(directory)
    names = sorted(name for name in check_store_files(directory) if name != MANIFEST_FILE)
    digests = on_cores(lambda name: file_sha256(directory / name), names)
    files: dict[str, dict[str, object]] = {
        name: {"bytes": (directory / name).stat().st_size, "sha256": digest}
        for name, digest in zip(names, digests, strict=True)}
    text = json.dumps({"schema": MANIFEST_SCHEMA, "files": files}, indent=1, sort_keys=True) + "\n"
    # Written beside and renamed over the marker (no atomic_path: it calls this module): whole or not at all.
    partial = directory / f".{MANIFEST_FILE}.writing-{uuid.uuid4().hex[:8]}"
    try:
        partial.write_text(text)
        os.replace(partial, directory / MANIFEST_FILE)
    finally:
        partial.unlink(missing_ok=True)
    return files


def verify_manifest(directory: str | Path) -> list[str]:
    """The files the manifest of ``directory`` lists, each checked: present, a regular file, of its size and
    SHA-256; the first that is not is an :class:`IntegrityError` naming it, as is a missing, empty or
    malformed manifest."""
    directory = Path(directory)
    listed = _listed(directory)
    present = check_store_files(directory)  # links and special files anywhere in it are refused first
    for name, entry in listed.items():
        if name not in present:
            raise IntegrityError(f"{directory}: {name} is missing; correct the scan again to restore it")
        if present[name] != entry["bytes"]:
            raise IntegrityError(f"{directory}: {name} has {present[name]:,} bytes, not the {entry['bytes']:,} "
                                 "written; correct the scan again to restore it")
    names = sorted(listed)
    digests = on_cores(lambda name: file_sha256(directory / name), names)
    for name, digest in zip(names, digests, strict=True):
        if digest != listed[name]["sha256"]:
            raise IntegrityError(f"{directory}: {name} is not the file written there (edited or replaced); "
                                 "correct the scan again to restore it")
    return names


def _listed(directory: Path) -> dict[str, dict[str, object]]:
    """The manifest's entries (relative POSIX path -> bytes, sha256), checked for form."""
    path = directory / MANIFEST_FILE
    try:
        info = path.lstat()
        if not stat.S_ISREG(info.st_mode) or info.st_size > MAX_METADATA_BYTES:
            raise IntegrityError(f"{path} is not a regular file of at most {MAX_METADATA_BYTES:,} bytes; correct "
                                 "the scan again")
        text = path.read_bytes() if info.st_size else b""
    except OSError as exc:
        raise IntegrityError(f"{directory}: its manifest {MANIFEST_FILE} cannot be read ({exc.strerror or exc}); "
                             "correct the scan again") from None
    return manifest_entries(text, str(directory))


def manifest_entries(text: bytes, where: str) -> dict[str, dict[str, object]]:
    """The entries of a manifest's bytes (relative POSIX path -> bytes, sha256), checked for form; an empty,
    malformed or foreign manifest is an :class:`IntegrityError` naming ``where``."""
    try:
        data = json.loads(text) if text else None
    except ValueError:
        data = {}
    files = data.get("files") if isinstance(data, dict) and data.get("schema") == MANIFEST_SCHEMA else None
    if data is None:
        raise IntegrityError(f"{where}: its files have no manifest (written before manifests, or interrupted); "
                             "correct the scan again")
    if not isinstance(files, dict) or not all(
            isinstance(name, str) and not name.startswith("/") and ".." not in name.split("/")
            and isinstance(entry, dict) and isinstance(entry.get("bytes"), int)
            and isinstance(entry.get("sha256"), str) and HEX_FINGERPRINT.fullmatch(entry["sha256"])
            for name, entry in files.items()):
        raise IntegrityError(f"{where}: its manifest {MANIFEST_FILE} is malformed; correct the scan again")
    return files


def unsealed(directory: str | Path) -> bool:
    """Whether ``directory`` has an empty marker: outputs whose manifest is still to be written."""
    path = Path(directory) / MANIFEST_FILE
    try:
        info = path.lstat()
    except OSError:
        return False
    return stat.S_ISREG(info.st_mode) and info.st_size == 0


def is_output_directory(directory: str | Path) -> bool:
    """Whether ``directory`` is marked as a scan's outputs (its marker exists, even empty or damaged): its
    files are then checked against the manifest, and an empty marker lists nothing to trust."""
    return os.path.lexists(Path(directory) / MANIFEST_FILE)
