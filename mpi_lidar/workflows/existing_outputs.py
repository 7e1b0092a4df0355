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
import os
from pathlib import Path
from typing import TypedDict

import zarr

from mpi_lidar.correction import ScanOutcome, ScanStatus
from mpi_lidar.correction.options import UnservedReason
from mpi_lidar.correction.outcome import scan_status
from mpi_lidar.locations import Location, location
from mpi_lidar.reporting.output_levels import covers
from mpi_lidar.reporting.point_cloud_files import cloud_placement
from mpi_lidar.storage.manifest import MANIFEST_FILE, verify_manifest
from mpi_lidar.storage.objects import list_files, published_damage, read_bytes, zarr_store
from mpi_lidar.workflows.archive_paths import SUMMARY_NAME


def has_outputs(target: Path | Location) -> bool:
    """Whether anything of a scan's outputs is at ``target`` (its ``corrected.zarr``, or in a store a manifest)."""
    if isinstance(target, Path):
        return (target / "corrected.zarr").exists()
    present = list_files(target)  # one listing of the scan's folder answers both (an absent object costs two)
    return MANIFEST_FILE in present or "corrected.zarr/zarr.json" in present


def has_files(target: Path | Location, names: list[str]) -> bool:
    """Whether every one of ``names`` is a file of ``target`` (one listing in a store)."""
    if isinstance(target, Path):
        return all((target / name).is_file() for name in names)
    present = list_files(target)
    return all(name in present for name in names)


def already_done(target: Path | Location, scan_sha: str, model_sha: str, options_sha: str,
                 outputs: str = "full", placement: str | None = None) -> bool:
    """Whether ``target`` holds this scan corrected by this model with these options, with at least the files
    of output level ``outputs`` and its point clouds' points placed as ``placement`` says
    (:func:`~mpi_lidar.reporting.point_cloud_files.cloud_placement`; None: the default). The level is no part of
    the options' hash: it never changes a pixel, so outputs written at a higher level are kept, and a lower level
    is corrected again to write the rest."""
    try:
        store = zarr_store(location(target).joinpath("corrected.zarr"))
        attrs = zarr.open_group(store=store, mode="r", zarr_format=3).attrs  # ours: v3, no probing for v2
    except Exception:  # no store, or a foreign one: not done
        return False
    written = attrs.get("outputs")  # absent in outputs written before output levels existed
    return (attrs.get("scan_sha256"), attrs.get("model_sha256"), attrs.get("options_sha256")) == (
        scan_sha, model_sha, options_sha) and covers(written if isinstance(written, str) else None, outputs) and (
        recorded_placement(dict(attrs)) == (placement or cloud_placement()))


def recorded_placement(attrs: dict[str, object]) -> str:
    """The point-cloud placement a ``corrected.zarr``'s attributes record (absent before it was: the default)."""
    placement = attrs.get("point_cloud_placement")
    return placement if isinstance(placement, str) else cloud_placement()


def output_folders(out_dir: Path, max_depth: int = 8) -> dict[Path, dict[str, object]]:
    """Every scan's output folder below a local ``out_dir`` (one holding a ``corrected.zarr``), with that store's
    attributes; the batch summary (``summary/``), staging and hidden folders are not looked into."""
    found: dict[Path, dict[str, object]] = {}
    for folder, subfolders, _ in os.walk(out_dir):
        here = Path(folder)
        depth = len(here.relative_to(out_dir).parts)
        metadata = here / "corrected.zarr" / "zarr.json"
        if metadata.is_file():
            try:
                attrs = json.loads(metadata.read_text()).get("attributes", {})
            except (OSError, ValueError, AttributeError):
                attrs = {}
            found[here] = attrs if isinstance(attrs, dict) else {}
            subfolders.clear()
            continue
        subfolders[:] = sorted(name for name in subfolders if not name.startswith(".") and depth < max_depth
                               and not (depth == 0 and name == SUMMARY_NAME))
    return found


def other_options(folders: dict[Path, dict[str, object]], options_sha: str, placement: str) -> dict[Path, str]:
    """The output folders made with other options or another point-cloud placement: each with what differs."""
    differing: dict[Path, str] = {}
    for folder, attrs in folders.items():
        recorded = str(attrs.get("options_sha256", "?"))
        if recorded != options_sha:
            differing[folder] = f"options {recorded[:12]}"
        elif recorded_placement(attrs) != placement:
            differing[folder] = f"point clouds with {recorded_placement(attrs)}"
    return differing


def earlier_outcome(folder: Path, attrs: dict[str, object], max_invalid_share: float) -> ScanOutcome | None:
    """A scan corrected by an earlier batch into the same ``--out`` (its folder and ``corrected.zarr``'s
    attributes), for the summary of the folder; None where its results cannot be read."""
    results = existing_results(folder)
    if results is None:
        return None
    name = str(attrs.get("scan_name") or folder.name)
    return ScanOutcome(str(folder), name, ScanStatus.SKIPPED, "kept from an earlier batch", output=str(folder),
                       counts=results["counts"], metrics=results["metrics"], notes=results["notes"],
                       kept_status=scan_status(results["counts"], max_invalid_share, results["unserved"]),
                       unserved=results["unserved"])


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
