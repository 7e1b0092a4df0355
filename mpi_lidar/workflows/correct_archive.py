"""Batch correction of an archive: one scan's outputs written atomically, a bad scan failing alone.

Per scan the outputs go into ``<out>/<scan name>/`` (``corrected.zarr``, report files, point clouds),
built under a staging name and renamed into place (:mod:`mpi_lidar.storage.atomic`), so a scan's outputs
are all there or not at all. A scan already corrected by the same model with the same options (same content
hashes) is skipped. The loop runs on an executor (:mod:`mpi_lidar.workflows.executor`): in this process, as
one Dask task per scan, or as one Prefect task per scan in the flow; the command line, the pipeline and the
Prefect flow all call :func:`correct_archive`.
"""

from __future__ import annotations

import glob
import re
import time
from collections.abc import Callable
from functools import lru_cache
from pathlib import Path

import zarr
from distributed import Client

from mpi_lidar.correction import CorrectionOptions, ScanOutcome, ScanStatus, correct_scan, make_gate
from mpi_lidar.errors import MpiLidarError
from mpi_lidar.learning.model import CorrectionModel, load_model
from mpi_lidar.reporting.scan_report import scan_metrics, write_scan_outputs
from mpi_lidar.scans.scan import SCAN_SUFFIX, read_scan
from mpi_lidar.storage.atomic import remove_interrupted_staging
from mpi_lidar.workflows.executor import Executor, as_executor

SAFE_NAME = re.compile(r"^[A-Za-z0-9][A-Za-z0-9._-]{0,127}$")


def safe_scan_name(name: str) -> str:
    """The scan's name as an output directory name; anything that could escape the output directory is refused."""
    if not SAFE_NAME.match(name) or ".." in name:
        raise MpiLidarError(f"scan name {name!r} is not a safe directory name (letters, digits, . _ -); "
                            "rename the scan")
    return name


def _already_done(target: Path, scan_sha: str, model_sha: str, options_sha: str) -> bool:
    try:
        attrs = zarr.open_group(store=str(target / "corrected.zarr"), mode="r").attrs
    except Exception:  # no store, or a foreign one: not done
        return False
    return (attrs.get("scan_sha256"), attrs.get("model_sha256"), attrs.get("options_sha256")) == (
        scan_sha, model_sha, options_sha)


def process_scan(source: str | Path, model_dir: str | Path, out_dir: str | Path,
                 options: CorrectionOptions) -> ScanOutcome:
    """Correct one scan and write its outputs; any failure becomes a 'failed' outcome with its reason."""
    started = time.perf_counter()
    source = str(source)
    try:
        return _process_scan(source, Path(model_dir), Path(out_dir), options, started)
    except MpiLidarError as exc:
        return ScanOutcome(source, Path(source).name, ScanStatus.FAILED, str(exc),
                           seconds=time.perf_counter() - started)
    except (OSError, ValueError, KeyError) as exc:
        return ScanOutcome(source, Path(source).name, ScanStatus.FAILED, f"{type(exc).__name__}: {exc}",
                           seconds=time.perf_counter() - started)


@lru_cache(maxsize=4)
def _cached_model(model_dir: str) -> CorrectionModel:
    return load_model(model_dir)


def _process_scan(source: str, model_dir: Path, out_dir: Path, options: CorrectionOptions,
                  started: float) -> ScanOutcome:

    scan = read_scan(source)
    name = safe_scan_name(scan.name)
    target = out_dir / name
    model = _cached_model(str(model_dir))
    scan_sha, model_sha, options_sha = scan.content_sha256(), model.card.model_sha256, options.sha256()
    if _already_done(target, scan_sha, model_sha, options_sha):
        return ScanOutcome(source, name, ScanStatus.SKIPPED, "already corrected with this model and options",
                           output=str(target), seconds=time.perf_counter() - started)
    correction = correct_scan(scan, model, options)
    metrics = scan_metrics(scan, correction)
    identity = {"scan_sha256": scan_sha, "model_sha256": model_sha, "options_sha256": options_sha}
    notes = write_scan_outputs(target, scan, correction, metrics, identity, options)
    return ScanOutcome(source, name, ScanStatus.CORRECTED, output=str(target), counts=correction.counts(),
                       metrics=metrics,
                       seconds=time.perf_counter() - started, notes=tuple(notes))

# --- a batch ----------------------------------------------------------------------------------------------


def expand_archive(inputs: list[str]) -> list[str]:
    """Scan stores named directly, found in a directory, or matched by a glob; sorted and unique."""
    found: list[str] = []
    for item in inputs:
        path = Path(item)
        if glob.has_magic(item):
            matches = sorted(glob.glob(item))
            if not matches:
                raise MpiLidarError(f"{item} matches no scan; give *{SCAN_SUFFIX} stores, a directory or a glob")
            found += matches
        elif path.name.endswith(SCAN_SUFFIX) or (path.is_dir() and (path / "zarr.json").exists()):
            found.append(str(path))
        elif path.is_dir():
            found += sorted(str(p) for p in path.glob(f"*{SCAN_SUFFIX}"))
        else:
            raise MpiLidarError(f"{item} is not a scan store or a directory of *{SCAN_SUFFIX} stores")
    return sorted(dict.fromkeys(found))


def correct_archive(inputs: list[str], model_dir: str | Path, out_dir: str | Path, options: CorrectionOptions,
                    executor: Executor | Client | None = None, on_scan: Callable[[ScanOutcome], None] | None = None,
                    *, client: Client | None = None) -> list[ScanOutcome]:
    """Correct every scan, one call of :func:`process_scan` per scan on ``executor``; a bad scan fails alone.

    The executor runs the scans in this process (None), as Dask tasks (an executor or a ``client``, the same)
    or as the correction flow's Prefect tasks. Before any scan, a model that cannot be loaded or a gate that
    cannot be made fails the batch with one line, and staging directories an interrupted run left in
    ``out_dir`` are removed. ``on_scan`` sees each outcome as it finishes; the outcomes come back by source.
    """
    load_model(model_dir)  # a broken model fails the whole batch at once, with one clear line
    make_gate(options)
    out_dir = Path(out_dir)
    try:
        out_dir.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise MpiLidarError(f"cannot create output directory {out_dir}: {exc.strerror or exc}") from None
    sources = expand_archive(inputs)
    remove_interrupted_staging(out_dir)
    calls = [{"source": source, "model_dir": str(model_dir), "out_dir": str(out_dir), "options": options}
             for source in sources]
    outcomes: list[ScanOutcome] = []
    for _call, outcome in as_executor(executor if executor is not None else client).map(process_scan, calls):
        outcomes.append(outcome)
        if on_scan:
            on_scan(outcome)
    return sorted(outcomes, key=lambda o: o.source)
