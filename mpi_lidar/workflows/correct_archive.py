"""Batch correction of an archive: one scan's outputs written atomically, a bad scan failing alone.

Per scan the outputs (``corrected.zarr``, report files, point clouds) go into a directory named after the scan
store's path (:mod:`mpi_lidar.workflows.archive_paths`). Each scan's directory is built under a staging name and
renamed into place (:mod:`mpi_lidar.storage.atomic`), so a scan's outputs are all there or not at all. Scans
and ``out_dir`` may be object-store URLs (``s3://bucket/prefix``): outputs are then built the same way in a
temporary directory and published by their manifest, written last
(:mod:`mpi_lidar.workflows.remote_outputs`, :mod:`mpi_lidar.storage.objects`). A scan
already corrected by the same model with the same options, its outputs intact, is skipped
(:mod:`mpi_lidar.workflows.existing_outputs`). A batch holds its output directory for as long as it
runs (:class:`~mpi_lidar.storage.publication.OutputLock`): a second batch into the same ``out_dir`` at the same
time is refused with one line naming the run that holds it. A written scan is ``corrected``,
``unchanged`` (no pixel corrected) or ``degraded`` (more invalid pixels than ``max_invalid_share``), see
:func:`mpi_lidar.correction.outcome.scan_status`; which outcomes fail a batch is
:mod:`mpi_lidar.workflows.batch_failure`'s. The loop runs on an executor
(:mod:`mpi_lidar.workflows.executor`): in this process, as one Dask task per scan, or as one Prefect task per
scan in the flow; the command line, the pipeline and the Prefect flow all call :func:`correct_archive`.
"""

from __future__ import annotations

import ctypes
import time
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from functools import lru_cache
from pathlib import Path, PurePosixPath
from typing import TYPE_CHECKING

from mpi_lidar.correction import CorrectionOptions, ScanOutcome, ScanStatus, correct_scan, make_gate
from mpi_lidar.correction.outcome import scan_status, status_reason
from mpi_lidar.errors import MpiLidarError
from mpi_lidar.learning.model import CARD_FILE, MODEL_FILE, CorrectionModel, load_model
from mpi_lidar.locations import Location, location
from mpi_lidar.reporting.metrics import scan_metrics
from mpi_lidar.reporting.output_levels import check_outputs
from mpi_lidar.reporting.point_cloud_files import cloud_placement, point_cloud_files, point_cloud_formats
from mpi_lidar.reporting.scan_outputs import write_scan_outputs
from mpi_lidar.scans.store import STORED_MAPS_ABOVE_BYTES, read_scan
from mpi_lidar.storage.manifest import unsealed, write_manifest
from mpi_lidar.storage.objects import ObjectOutputLock, filesystem, store_error
from mpi_lidar.storage.publication import LocalOutputLock
from mpi_lidar.workflows.archive_paths import expand_archive, safe_output, safe_scan_name, scan_output_paths
from mpi_lidar.workflows.batch_failure import FAIL_ON, batch_failure, failing_outcomes, failure_line
from mpi_lidar.workflows.executor import Executor, as_executor
from mpi_lidar.workflows.existing_outputs import (
    already_done,
    earlier_outcome,
    existing_results,
    has_files,
    has_outputs,
    other_options,
    output_folders,
    outputs_damage,
)
from mpi_lidar.workflows.remote_outputs import written_at

if TYPE_CHECKING:
    from distributed import Client

# The batch's parts that callers import from here with correct_archive itself.
__all__ = [
    "FAIL_ON", "batch_failure", "correct_archive", "expand_archive", "failing_outcomes", "failure_line",
    "process_scan", "safe_scan_name", "scan_output_paths", "share_one_heap",
]

MAX_REASON_CHARS = 500


def _one_line(exc: Exception) -> str:
    """An exception as one line: a library error's message, anything else ``TypeName: message``."""
    lines = str(exc).strip().splitlines()
    message = lines[0].strip() if lines else ""
    if not isinstance(exc, MpiLidarError):
        message = f"{type(exc).__name__}: {message}" if message else type(exc).__name__
    return message if len(message) <= MAX_REASON_CHARS else message[:MAX_REASON_CHARS - 3] + "..."


def process_scan(source: str | Path, model_dir: str | Path, out_dir: str | Path, options: CorrectionOptions,
                 output: str | None = None, outputs: str = "full", point_clouds: tuple[str, ...] | None = None,
                 point_cloud_frame: str = "scanner", no_return_range_m: float | None = None) -> ScanOutcome:
    """Correct one scan and write its outputs into ``out_dir/output``; any failure becomes a 'failed' outcome.

    ``output`` is the scan's output directory relative to ``out_dir`` (:func:`scan_output_paths` of the
    whole batch); None derives it from ``source`` alone (its store name without the suffix). ``outputs`` is
    the output level (:data:`mpi_lidar.reporting.output_levels.OUTPUT_LEVELS`: full, light, data);
    ``point_clouds`` the point-cloud formats written at any level (``las``, ``laz``, ``ply``; None: the level's,
    ply and laz at full, laz at light, none at data), and a scan done before without one of them is corrected
    again; ``point_cloud_frame`` and ``no_return_range_m`` where their points lie
    (:func:`~mpi_lidar.reporting.point_cloud_files.write_point_clouds`), and a scan done before with others is
    corrected again. Every exception (any type: a damaged store, a bug, no memory) fails this scan alone with a one-line
    reason (``TypeName: message`` for other than the library's own errors); KeyboardInterrupt and SystemExit
    stop it.
    """
    started = time.perf_counter()
    source = str(source)
    try:
        if output is None:
            output = scan_output_paths([source])[source]
        out = location(out_dir)
        base = out.local_path() if out.is_local else out
        return _process_scan(source, str(model_dir), safe_output(base, output), options, started,
                             outputs, point_clouds, bundle_dir=base, output=output,
                             placement=(point_cloud_frame, no_return_range_m))
    except Exception as exc:  # one bad scan, whatever went wrong, must not stop the batch
        return ScanOutcome(source, location(source).name, ScanStatus.FAILED, _one_line(exc),
                           seconds=time.perf_counter() - started)


# glibc gives every thread that allocates its own heap (arena), and memory freed in one arena is reused only
# by the threads of that arena. A scan's tiles are allocated by this thread, the plane fits' threads, zarr's
# decoders and XGBoost's threads in turn, so each arena ends up holding a share of the freed tiles: at
# 4000 x 4000 that was 50-160 MiB of the peak resident set (docs/results/correction.md). One arena for all threads
# reuses them wherever they were freed, at the same speed on the 2-core machine. (A fixed mmap threshold
# would give them back to the system too, but costs a quarter more time in page faults.)
_M_ARENA_MAX = -8  # mallopt's parameter number, from glibc's malloc.h


@lru_cache(maxsize=1)
def share_one_heap() -> bool:
    """Make every thread of this process allocate from one heap (glibc; elsewhere nothing is done), so memory
    freed by one thread serves the next. True where the allocator took the setting. Called by every scan of
    an archive, once per process: it holds for the threads started afterwards."""
    try:
        return bool(ctypes.CDLL(None).mallopt(_M_ARENA_MAX, 1))
    except (OSError, AttributeError):  # no C library to load, or one without mallopt (macOS, musl)
        return False


# Per model file (a local model's two; a URL's card): what changes when it is written again.
ModelSignature = tuple[tuple[object, ...] | None, ...]


def _cached_model(model_dir: str) -> CorrectionModel:
    """The model of ``model_dir``, loaded once per process: every scan of a batch run here, or of one Dask
    worker, shares it. Its files' sizes and modification times (in an object store, its card's version) are
    part of the key, so a model replaced at the same path or URL is loaded again."""
    return _load_model(str(model_dir), _model_files_signature(str(model_dir)))


@lru_cache(maxsize=4)
def _load_model(model_dir: str, _signature: ModelSignature) -> CorrectionModel:
    return load_model(model_dir)


def _model_files_signature(model_dir: str) -> ModelSignature:
    where = location(model_dir)
    if not where.is_local:
        return (_published_card_version(where),)
    signature: list[tuple[object, ...] | None] = []
    for name in (MODEL_FILE, CARD_FILE):
        try:
            stat = (where.local_path() / name).stat()
            signature.append((stat.st_ino, stat.st_size, stat.st_mtime_ns))
        except OSError:  # load_model says what is missing
            signature.append(None)
    return tuple(signature)


# What a store's HEAD gives that changes when an object is written again: S3's ETag (the content's digest) and
# time, and the same under gcsfs's and adlfs's names.
_VERSION_KEYS = ("ETag", "etag", "LastModified", "last_modified", "updated", "size")


def _published_card_version(model_dir: Location) -> tuple[object, ...] | None:
    """The version of a model's card in an object store, by one HEAD request; None where there is none (loading
    the model says so). The card is published last and names the model file's hash, so a model deleted and
    trained again at the same URL has another card."""
    card = model_dir.joinpath(CARD_FILE)
    try:
        info = filesystem(card).info(card.path)
    except FileNotFoundError:
        return None
    except Exception as exc:  # botocore raises many types
        raise store_error(card, exc, "read") from None
    return tuple(str(info[key]) for key in _VERSION_KEYS if key in info)


def _process_scan(source: str, model_dir: str, target: Path | Location, options: CorrectionOptions,
                  started: float, outputs: str = "full", point_clouds: tuple[str, ...] | None = None,
                  bundle_dir: Path | Location | None = None, output: str = "",
                  placement: tuple[str, float | None] = ("scanner", None)) -> ScanOutcome:
    share_one_heap()
    placed = cloud_placement(*placement)
    scan = read_scan(source, stored_above_bytes=STORED_MAPS_ABOVE_BYTES)  # a large scan stays in its store
    name = safe_scan_name(scan.name)  # not the output directory any more, but it names the scan everywhere
    model = _cached_model(str(model_dir))
    model_sha, options_sha = model.card.model_sha256, options.sha256()
    damage = None
    found = has_outputs(target)
    if found or not scan.in_memory():
        scan_sha = scan.content_sha256()
        # What is skipped is verified first: every file the outputs' manifest lists, as written.
        damage = outputs_damage(target) if found else None
        done = damage is None and already_done(target, scan_sha, model_sha, options_sha, outputs, placed) and has_files(
            target, list(point_cloud_files(scan, outputs, point_clouds)))
        existing = existing_results(target) if done else None
        if existing is not None:
            counts, kept_reason = existing["counts"], existing["unserved"]
            return ScanOutcome(source, name, ScanStatus.SKIPPED, "already corrected with this model and options",
                               output=str(target), counts=counts, metrics=existing["metrics"],
                               seconds=time.perf_counter() - started, notes=existing["notes"],
                               kept_status=scan_status(counts, options.max_invalid_share, kept_reason),
                               unserved=kept_reason)
        correction = correct_scan(scan, model, options)
    else:
        # Nothing there to skip: the scan's identity is hashed on a thread beside the correction (hashlib
        # releases the GIL). A scan kept in its store is hashed first instead: its reads would double.
        with ThreadPoolExecutor(1) as hashing:
            pending = hashing.submit(scan.content_sha256)
            correction = correct_scan(scan, model, options)
            scan_sha = pending.result()
    identity = {"scan_sha256": scan_sha, "model_sha256": model_sha, "options_sha256": options_sha,
                "point_cloud_placement": placed}
    # A scan in memory is measured on a thread while its outputs are written; one in its store before (its
    # band of decoded rows would come on top of the writing's memory).
    with ThreadPoolExecutor(1) as beside, written_at(target, bundle_dir, output) as (directory, bundle):
        measuring = beside.submit(scan_metrics, scan, correction) if scan.in_memory() else None
        metrics = scan_metrics(scan, correction) if measuring is None else {}
        notes = write_scan_outputs(directory, scan, correction, metrics if measuring is None else measuring,
                                   identity, options, outputs, point_clouds=point_clouds, bundle_dir=bundle,
                                   point_cloud_frame=placement[0], no_return_range_m=placement[1])
        metrics = metrics if measuring is None else measuring.result()
        if unsealed(directory):  # atomic_path wrote the manifest with the outputs; a marker left empty gets it now
            write_manifest(directory)
    if damage is not None:
        notes = [*notes, f"existing outputs were damaged, corrected again ({damage})"]
    counts = correction.counts()
    reason = None if correction.unserved is None else correction.unserved.reason
    status = scan_status(counts, options.max_invalid_share, reason)
    return ScanOutcome(source, name, status, status_reason(status, counts, correction.unserved), output=str(target),
                       counts=counts, metrics=metrics, seconds=time.perf_counter() - started, notes=tuple(notes),
                       unserved=reason)


def correct_archive(inputs: list[str], model_dir: str | Path, out_dir: str | Path,
                    options: CorrectionOptions | None = None, executor: Executor | Client | None = None,
                    on_scan: Callable[[ScanOutcome], None] | None = None, *, client: Client | None = None,
                    outputs: str = "full", point_clouds: tuple[str, ...] | list[str] | None = None,
                    on_done: Callable[[list[ScanOutcome]], object] | None = None, point_cloud_frame: str = "scanner",
                    no_return_range_m: float | None = None, replace_options: bool = False) -> list[ScanOutcome]:
    """Correct every scan, one call of :func:`process_scan` per scan on ``executor``; a bad scan fails alone.

    The executor runs the scans in this process (None), as Dask tasks (an executor or a ``client``, the same)
    or as the correction flow's Prefect tasks. Before any scan, and before anything is written, a model that
    cannot be loaded, a gate that cannot be made or two scans that would write the same output directory
    (:func:`scan_output_paths`) fail the batch with one line; then staging directories an interrupted run
    left in ``out_dir`` (and in the folders of nested outputs) are removed. ``on_scan`` sees each outcome as
    it finishes; the outcomes come back by source. ``outputs`` is the output level of every scan
    (:data:`mpi_lidar.reporting.output_levels.OUTPUT_LEVELS`); the command line and the correction flow default
    to ``light`` (:data:`~mpi_lidar.reporting.output_levels.DEFAULT_OUTPUTS`), the pipeline writes ``full``.
    ``point_clouds``: the point-cloud formats every scan writes (``las``, ``laz``, ``ply``) at any level;
    None: the level's, ply and laz at full, laz at light, none at data; ``point_cloud_frame`` and
    ``no_return_range_m`` where their points lie. ``options`` None: the defaults.
    A local ``out_dir`` holding scans corrected with other options or point-cloud settings is refused before
    anything is written (:func:`refuse_other_options`), unless ``replace_options``: this batch's scans then get
    the new ones and the others keep theirs. ``on_done`` sees the outcomes while the batch still holds ``out_dir``
    (:class:`~mpi_lidar.storage.publication.OutputLock`): the place for its summary; in a local ``out_dir`` they
    include the scans earlier batches left there (skipped, "kept from an earlier batch"), so it counts every
    scan of the folder.
    """
    options = options or CorrectionOptions()
    level = check_outputs(outputs)
    point_clouds = None if point_clouds is None else point_cloud_formats(level, point_clouds)
    _cached_model(str(model_dir))  # a broken model fails the whole batch at once, with one clear line
    make_gate(options)
    out = location(out_dir)
    sources = expand_archive(inputs)
    directories = scan_output_paths(sources)
    placed = cloud_placement(point_cloud_frame, no_return_range_m)
    if out.is_local and not replace_options:
        refuse_other_options(out.local_path(), options.sha256(), placed)
    lock = LocalOutputLock(_created(out.local_path())) if out.is_local else ObjectOutputLock(out)
    with lock.hold():  # a second batch into out_dir is refused while this one runs
        for folder in sorted({PurePosixPath(output).parent for output in directories.values()}):
            if ".." not in folder.parts:
                lock.remove_interrupted(folder)
        calls = [{"source": source, "model_dir": str(model_dir), "out_dir": out.url, "options": options,
                  "output": directories[source], "outputs": level, "point_clouds": point_clouds,
                  "point_cloud_frame": point_cloud_frame, "no_return_range_m": no_return_range_m}
                 for source in sources]
        outcomes: list[ScanOutcome] = []
        for _call, outcome in as_executor(executor if executor is not None else client).map(process_scan, calls):
            outcomes.append(outcome)
            if on_scan:
                on_scan(outcome)
        outcomes.sort(key=lambda o: o.source)
        if on_done:  # the batch summary, written while the output directory is still this batch's
            on_done(outcomes + (_earlier_outcomes(out.local_path(), outcomes, options) if out.is_local else []))
    return outcomes


def refuse_other_options(out_dir: Path, options_sha: str, placement: str) -> None:
    """Refuse, with one line, a batch into a local ``out_dir`` that holds scans corrected with other options or
    point-cloud settings (their outputs' ``corrected.zarr`` records them): one folder would mix them unnoticed."""
    if not out_dir.is_dir():
        return
    differing = other_options(output_folders(out_dir), options_sha, placement)
    if differing:
        folder, what = next(iter(sorted(differing.items())))
        others = f" and {len(differing) - 1} other scan(s)" if len(differing) > 1 else ""
        raise MpiLidarError(f"--out {out_dir} holds {folder.relative_to(out_dir).as_posix()}{others} corrected with "
                            f"other settings ({what}); give the same options, another --out, or --replace-options "
                            "to correct these scans with the new ones (the summary then says which options made "
                            "each scan)")


def _earlier_outcomes(out_dir: Path, outcomes: list[ScanOutcome], options: CorrectionOptions) -> list[ScanOutcome]:
    """The scans earlier batches left in ``out_dir`` that this batch did not touch, for the summary."""
    this_batch = {Path(o.output).resolve() for o in outcomes if o.output}
    found = [earlier_outcome(folder, attrs, options.max_invalid_share)
             for folder, attrs in output_folders(out_dir).items() if folder.resolve() not in this_batch]
    return sorted((o for o in found if o is not None), key=lambda o: o.source)


def _created(out_dir: Path) -> Path:
    try:
        out_dir.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise MpiLidarError(f"cannot create output directory {out_dir}: {exc.strerror or exc}") from None
    return out_dir
