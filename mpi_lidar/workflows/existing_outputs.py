"""What a re-run finds in a scan's output directory: whether its outputs can be kept, and their results.

A scan already corrected by the same model with the same options (same content hashes) is skipped, and its
counts, metrics and notes are read back from its ``metrics.json``, but only if every file its outputs' manifest
lists (``corrected.zarr``'s metadata and chunks, ``metrics.json``, the report, images and point clouds) is
still the file written there (:mod:`mpi_lidar.storage.manifest`); outputs with a file missing, edited or
replaced are corrected again, with a note saying why (:func:`mpi_lidar.workflows.correct_archive.process_scan`).

Outputs in an object store count only where published (their manifest there); a re-run checks that every object
the manifest lists is there with its size (:func:`mpi_lidar.storage.objects.published_damage`: one listing and
one read per scan, not every byte; ``mpi-lidar verify`` reads every byte).
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import TypedDict

import zarr

from mpi_lidar.correction.options import UnservedReason
from mpi_lidar.locations import Location, location
from mpi_lidar.reporting.output_levels import covers
from mpi_lidar.storage.manifest import MANIFEST_FILE, verify_manifest
from mpi_lidar.storage.objects import exists, list_files, published_damage, read_bytes, zarr_store


def has_outputs(target: Path | Location) -> bool:
    """Whether anything of a scan's outputs is at ``target`` (its ``corrected.zarr``, or in a store a manifest)."""
    if isinstance(target, Path):
        return (target / "corrected.zarr").exists()
    return exists(target.joinpath(MANIFEST_FILE)) or exists(target.joinpath("corrected.zarr", "zarr.json"))


def has_files(target: Path | Location, names: list[str]) -> bool:
    """Whether every one of ``names`` is a file of ``target`` (one listing in a store)."""
    if isinstance(target, Path):
        return all((target / name).is_file() for name in names)
    present = list_files(target)
    return all(name in present for name in names)


def already_done(target: Path | Location, scan_sha: str, model_sha: str, options_sha: str,
                 outputs: str = "full") -> bool:
    """Whether ``target`` holds this scan corrected by this model with these options, with at least the files
    of output level ``outputs``. The level is no part of the options' hash: it never changes a pixel, so
    outputs written at a higher level are kept, and a lower level is corrected again to write the rest."""
    try:
        store = zarr_store(location(target).joinpath("corrected.zarr"))
        attrs = zarr.open_group(store=store, mode="r").attrs
    except Exception:  # no store, or a foreign one: not done
        return False
    written = attrs.get("outputs")  # absent in outputs written before output levels existed
    return (attrs.get("scan_sha256"), attrs.get("model_sha256"), attrs.get("options_sha256")) == (
        scan_sha, model_sha, options_sha) and covers(written if isinstance(written, str) else None, outputs)


def outputs_damage(target: Path | Location) -> str | None:
    """None where every file the manifest of ``target`` lists is the file written there; else why not."""
    if not isinstance(target, Path):
        return published_damage(target)
    try:
        verify_manifest(target)
    except OSError as exc:  # IntegrityError (a StoreError), or a file that vanished while it was read
        return str(exc).splitlines()[0] if str(exc) else type(exc).__name__
    return None


class ExistingResults(TypedDict):
    counts: dict[str, int]
    metrics: dict[str, dict[str, float]]
    notes: tuple[str, ...]
    unserved: UnservedReason | None


def existing_results(target: Path | Location) -> ExistingResults | None:
    """Counts, metrics and notes of a scan's existing outputs (its ``metrics.json``); None if unreadable.

    Outputs are written whole or not at all, so an unreadable ``metrics.json`` means they were damaged or
    are not ours: the scan is then corrected again rather than skipped with no numbers.
    """
    try:
        text = ((target / "metrics.json").read_bytes() if isinstance(target, Path)
                else read_bytes(target.joinpath("metrics.json")))
        data = json.loads(text or b"")
    except (OSError, ValueError):
        return None
    counts, metrics, notes = (data.get(key) if isinstance(data, dict) else None
                              for key in ("counts", "metrics", "notes"))
    if not (isinstance(counts, dict) and all(isinstance(n, int) for n in counts.values())):
        return None
    unserved = data.get("unserved")
    reason = unserved.get("reason") if isinstance(unserved, dict) else None
    if unserved is not None and reason not in set(UnservedReason):
        return None
    return {"counts": {str(k): int(n) for k, n in counts.items()},
            "metrics": metrics if isinstance(metrics, dict) else {},
            "notes": tuple(str(n) for n in notes) if isinstance(notes, list) else (),
            "unserved": None if reason is None else UnservedReason(reason)}
