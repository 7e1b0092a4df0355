"""Batch correction of an archive: one scan's outputs written atomically, a bad scan failing alone.

Per scan the outputs (``corrected.zarr``, report files, point clouds) go into a directory named after the
scan store's path relative to the common root of the batch's inputs (the deepest directory holding all their
parent directories), with the ``.scan.zarr`` (or ``.zarr``) suffix removed: a directory of scans keeps their
names (``scenes/cornered_board.scan.zarr`` -> ``<out>/cornered_board/``), an archive with one folder per day
gets nested directories (``day1/frame.scan.zarr`` -> ``<out>/day1/frame/``). Every component must be a safe
name (letters, digits, ``. _ -``, starting with a letter or digit), or that scan fails. ``<out>/summary/`` is
the batch summary's: a scan (or folder) whose first component would be ``summary`` goes to ``summary.scan``
instead (``summary.scan.zarr`` -> ``<out>/summary.scan/``), so neither overwrites the other. Two inputs
mapping to one directory, or one inside another's, are refused before anything is written (the scan's own
``name`` attribute no longer decides where its outputs go, but it must still be a safe name: it names the
scan in every report). Each scan's directory is built under a staging name and renamed into place
(:mod:`mpi_lidar.storage.atomic`), so a scan's outputs are all there or not at all.

A scan already corrected by the same model with the same options (same content hashes) is skipped, and its
counts, metrics and notes are read back from its ``metrics.json``, but only if every file its outputs' manifest
lists (``corrected.zarr``'s metadata and chunks, ``metrics.json``, the report, images and point clouds) is
still the file written there (:mod:`mpi_lidar.storage.manifest`); outputs with a file missing, edited or
replaced are corrected again, with a note saying why. A batch holds its output directory for as long as it
runs (:func:`output_lock`): a second batch into the same ``out_dir`` at the same time is refused with one
line naming the run that holds it. A written scan is ``corrected``,
``unchanged`` (no pixel corrected) or ``degraded`` (more invalid pixels than ``max_invalid_share``), see
:func:`mpi_lidar.correction.outcome.scan_status`. The loop runs on an executor
(:mod:`mpi_lidar.workflows.executor`): in this process, as one Dask task per scan, or as one Prefect task per
scan in the flow; the command line, the pipeline and the Prefect flow all call :func:`correct_archive`.
"""

from __future__ import annotations

import ctypes
import fcntl
import glob
import json
import os
import re
import socket
import threading
import time
from collections.abc import Callable, Iterator, Sequence
from concurrent.futures import ThreadPoolExecutor
from contextlib import contextmanager
from functools import lru_cache
from pathlib import Path, PurePosixPath
from typing import TYPE_CHECKING, TypedDict

import zarr

from mpi_lidar.correction import CorrectionOptions, ScanOutcome, ScanStatus, correct_scan, make_gate
from mpi_lidar.correction.options import UnservedReason
from mpi_lidar.correction.outcome import invalid_share, scan_status
from mpi_lidar.errors import MpiLidarError
from mpi_lidar.learning.model import CARD_FILE, MODEL_FILE, CorrectionModel, load_model
from mpi_lidar.reporting.metrics import scan_metrics
from mpi_lidar.reporting.output_levels import check_outputs, covers
from mpi_lidar.reporting.point_cloud_files import point_cloud_files, point_cloud_formats
from mpi_lidar.reporting.scan_outputs import write_scan_outputs
from mpi_lidar.scans.store import SCAN_SUFFIX, STORED_MAPS_ABOVE_BYTES, read_scan
from mpi_lidar.storage.atomic import remove_interrupted_staging
from mpi_lidar.storage.manifest import unsealed, verify_manifest, write_manifest
from mpi_lidar.workflows.executor import Executor, as_executor

if TYPE_CHECKING:
    from distributed import Client

SAFE_NAME = re.compile(r"[A-Za-z0-9][A-Za-z0-9._-]{0,127}")  # fullmatch: "$" would let a final newline pass
SUMMARY_NAME = "summary"  # <out>/summary/: the batch summary (mpi_lidar.reporting.batch_report)
RESERVED_SUFFIX = ".scan"  # a scan whose output would be <out>/summary/ goes to <out>/summary.scan/ instead
MAX_REASON_CHARS = 500
LOCK_FILE = ".mpi-lidar-correct.lock"  # <out>/: held by the batch writing there (output_lock)


def safe_scan_name(name: str, what: str = "scan name", fix: str = "rename the scan") -> str:
    """``name`` as a directory name; anything that could escape the output directory is refused."""
    if not isinstance(name, str) or not SAFE_NAME.fullmatch(name) or ".." in name:
        raise MpiLidarError(f"{what} {name!r} is not a safe directory name (letters, digits, . _ -); {fix}")
    return name


def _store_stem(name: str) -> str:
    for suffix in (SCAN_SUFFIX, ".zarr"):
        if name.endswith(suffix):
            return name.removesuffix(suffix)
    return name


def scan_output_paths(sources: list[str]) -> dict[str, str]:
    """Each source's output directory, relative to the output directory (POSIX, ``/``-separated).

    The path of each store relative to the common root of all the sources' parent directories, suffix
    removed, a first component ``summary`` renamed ``summary.scan`` (see the module docstring). The
    components are not checked here (an unsafe one fails its scan alone, in :func:`process_scan`); two
    sources mapping to one directory, or one into another's (compared without case, as a case-insensitive
    file system would), are refused with one error naming both, before anything is written.
    """
    if not sources:
        return {}
    absolute = {source: Path(os.path.abspath(source)) for source in sources}
    root = Path(os.path.commonpath([str(path.parent) for path in absolute.values()]))
    outputs: dict[str, str] = {}
    for source, path in absolute.items():
        parts = list(path.relative_to(root).parts)
        parts[-1] = _store_stem(parts[-1])
        if parts[0].casefold() == SUMMARY_NAME:
            parts[0] += RESERVED_SUFFIX
        outputs[source] = "/".join(parts)
    _refuse_collisions(outputs)
    return outputs


def _refuse_collisions(outputs: dict[str, str]) -> None:
    owner: dict[str, str] = {}
    for source, output in sorted(outputs.items()):
        key = output.casefold()
        if key in owner:
            raise MpiLidarError(f"scans {owner[key]} and {source} would both write {output}/; "
                                "correct them in separate batches or rename one")
        owner[key] = source
    for source, output in sorted(outputs.items()):
        for parent in PurePosixPath(output.casefold()).parents:
            if str(parent) in owner:
                raise MpiLidarError(f"scan {source} would write {output}/ inside the outputs of "
                                    f"{owner[str(parent)]} ({outputs[owner[str(parent)]]}/); correct them in "
                                    "separate batches or move one")


def _safe_output(out_dir: Path, output: str) -> Path:
    """``out_dir`` joined with ``output`` after every component passed the safe-name rule."""
    for part in output.split("/"):
        safe_scan_name(part, "output directory component",
                       f"rename that folder or scan store (output {output!r})")
    return out_dir.joinpath(*output.split("/"))


def _already_done(target: Path, scan_sha: str, model_sha: str, options_sha: str, outputs: str = "full") -> bool:
    """Whether ``target`` holds this scan corrected by this model with these options, with at least the files
    of output level ``outputs``. The level is no part of the options' hash: it never changes a pixel, so
    outputs written at a higher level are kept, and a lower level is corrected again to write the rest."""
    try:
        attrs = zarr.open_group(store=str(target / "corrected.zarr"), mode="r").attrs
    except Exception:  # no store, or a foreign one: not done
        return False
    written = attrs.get("outputs")  # absent in outputs written before output levels existed
    return (attrs.get("scan_sha256"), attrs.get("model_sha256"), attrs.get("options_sha256")) == (
        scan_sha, model_sha, options_sha) and covers(written if isinstance(written, str) else None, outputs)


def _outputs_damage(target: Path) -> str | None:
    """None where every file the manifest of ``target`` lists is the file written there; else why not."""
    try:
        verify_manifest(target)
    except OSError as exc:  # IntegrityError (a StoreError), or a file that vanished while it was read
        return str(exc).splitlines()[0] if str(exc) else type(exc).__name__
    return None


class _Existing(TypedDict):
    counts: dict[str, int]
    metrics: dict[str, dict[str, float]]
    notes: tuple[str, ...]
    unserved: UnservedReason | None


def _existing_results(target: Path) -> _Existing | None:
    """Counts, metrics and notes of a scan's existing outputs (its ``metrics.json``); None if unreadable.

    Outputs are written whole or not at all, so an unreadable ``metrics.json`` means they were damaged or
    are not ours: the scan is then corrected again rather than skipped with no numbers.
    """
    try:
        data = json.loads((target / "metrics.json").read_text())
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


def _one_line(exc: Exception) -> str:
    """An exception as one line: a library error's message, anything else ``TypeName: message``."""
    lines = str(exc).strip().splitlines()
    message = lines[0].strip() if lines else ""
    if not isinstance(exc, MpiLidarError):
        message = f"{type(exc).__name__}: {message}" if message else type(exc).__name__
    return message if len(message) <= MAX_REASON_CHARS else message[:MAX_REASON_CHARS - 3] + "..."


def process_scan(source: str | Path, model_dir: str | Path, out_dir: str | Path, options: CorrectionOptions,
                 output: str | None = None, outputs: str = "full",
                 point_clouds: tuple[str, ...] | None = None) -> ScanOutcome:
    """Correct one scan and write its outputs into ``out_dir/output``; any failure becomes a 'failed' outcome.

    ``output`` is the scan's output directory relative to ``out_dir`` (:func:`scan_output_paths` of the
    whole batch); None derives it from ``source`` alone (its store name without the suffix). ``outputs`` is
    the output level (:data:`mpi_lidar.reporting.output_levels.OUTPUT_LEVELS`: full, light, data);
    ``point_clouds`` the point-cloud formats written at any level (``las``, ``laz``, ``ply``; None: ply and
    las at level full, none below), and a scan done before without one of them is corrected again. Every
    exception (any type: a damaged store, a bug, no memory) fails this scan alone with a one-line reason
    (``TypeName: message`` for other than the library's own errors); KeyboardInterrupt and SystemExit stop it.
    """
    started = time.perf_counter()
    source = str(source)
    try:
        if output is None:
            output = scan_output_paths([source])[source]
        return _process_scan(source, Path(model_dir), _safe_output(Path(out_dir), output), options, started,
                             outputs, point_clouds, bundle_dir=Path(out_dir))
    except Exception as exc:  # one bad scan, whatever went wrong, must not stop the batch
        return ScanOutcome(source, Path(source).name, ScanStatus.FAILED, _one_line(exc),
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


def _cached_model(model_dir: str) -> CorrectionModel:
    """The model of ``model_dir``, loaded once per process: every scan of a batch run here, or of one Dask
    worker, shares it. Its files' sizes and modification times are part of the key, so a model replaced
    at the same path is loaded again."""
    return _load_model(str(model_dir), _model_files_signature(Path(model_dir)))


@lru_cache(maxsize=4)
def _load_model(model_dir: str, _signature: tuple[tuple[int, int, int] | None, ...]) -> CorrectionModel:
    return load_model(model_dir)


def _model_files_signature(model_dir: Path) -> tuple[tuple[int, int, int] | None, ...]:
    signature: list[tuple[int, int, int] | None] = []
    for name in (MODEL_FILE, CARD_FILE):
        try:
            stat = (model_dir / name).stat()
            signature.append((stat.st_ino, stat.st_size, stat.st_mtime_ns))
        except OSError:  # load_model says what is missing
            signature.append(None)
    return tuple(signature)


def _process_scan(source: str, model_dir: Path, target: Path, options: CorrectionOptions,
                  started: float, outputs: str = "full", point_clouds: tuple[str, ...] | None = None,
                  bundle_dir: Path | None = None) -> ScanOutcome:
    share_one_heap()
    scan = read_scan(source, stored_above_bytes=STORED_MAPS_ABOVE_BYTES)  # a large scan stays in its store
    name = safe_scan_name(scan.name)  # not the output directory any more, but it names the scan everywhere
    model = _cached_model(str(model_dir))
    model_sha, options_sha = model.card.model_sha256, options.sha256()
    damage = None
    if (target / "corrected.zarr").exists() or not scan.in_memory():
        scan_sha = scan.content_sha256()
        # What is skipped is verified first: every file the outputs' manifest lists, as written.
        damage = _outputs_damage(target) if (target / "corrected.zarr").exists() else None
        done = damage is None and _already_done(target, scan_sha, model_sha, options_sha, outputs) and all(
            (target / name).is_file() for name in point_cloud_files(scan, outputs, point_clouds))
        existing = _existing_results(target) if done else None
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
    identity = {"scan_sha256": scan_sha, "model_sha256": model_sha, "options_sha256": options_sha}
    # A scan in memory is measured on a thread while its outputs are written; one in its store before (its
    # band of decoded rows would come on top of the writing's memory).
    with ThreadPoolExecutor(1) as beside:
        measuring = beside.submit(scan_metrics, scan, correction) if scan.in_memory() else None
        metrics = scan_metrics(scan, correction) if measuring is None else {}
        notes = write_scan_outputs(target, scan, correction, metrics if measuring is None else measuring, identity,
                                   options, outputs, point_clouds=point_clouds, bundle_dir=bundle_dir)
        metrics = metrics if measuring is None else measuring.result()
    if unsealed(target):  # atomic_path wrote the manifest with the outputs; a marker left empty gets it now
        write_manifest(target)
    if damage is not None:
        notes = [*notes, f"existing outputs were damaged, corrected again ({damage})"]
    counts = correction.counts()
    reason = None if correction.unserved is None else correction.unserved.reason
    return ScanOutcome(source, name, scan_status(counts, options.max_invalid_share, reason),
                       "" if correction.unserved is None else correction.unserved.message, output=str(target),
                       counts=counts, metrics=metrics, seconds=time.perf_counter() - started, notes=tuple(notes),
                       unserved=reason)

# --- a batch ----------------------------------------------------------------------------------------------


def expand_archive(inputs: list[str]) -> list[str]:
    """Scan stores named directly, found in a directory, or matched by a glob; sorted and unique.

    Refused with one line, before anything is read or written: a path that does not exist, a glob that matches
    no scan store, a directory that holds none, and a file of another tool (pointed to ``import-scan``).
    """
    found: list[str] = []
    for item in inputs:
        path = Path(item)
        if glob.has_magic(item):
            matches = [m for m in sorted(glob.glob(item)) if _is_scan_store(Path(m))]
            if not matches:
                raise MpiLidarError(f"{item} matches no scan store; give *{SCAN_SUFFIX} stores, a directory or a "
                                    f"glob of them{_import_hint(sorted(glob.glob(item)))}")
            found += matches
        elif _is_scan_store(path):
            found.append(str(path))
        elif not path.exists():
            raise MpiLidarError(f"{item} does not exist; give *{SCAN_SUFFIX} stores, a directory or a glob of them")
        elif path.is_dir():
            stores = sorted(str(p) for p in path.glob(f"*{SCAN_SUFFIX}") if _is_scan_store(p))
            if not stores:
                raise MpiLidarError(f"directory {item} holds no *{SCAN_SUFFIX} store"
                                    f"{_import_hint([str(p) for p in path.iterdir()])}")
            found += stores
        else:
            raise MpiLidarError(f"{item} is not a scan store (*{SCAN_SUFFIX}){_import_hint([item])}")
    return sorted(dict.fromkeys(found))


def _is_scan_store(path: Path) -> bool:
    """A Zarr store (its ``zarr.json``), or anything named ``*.scan.zarr`` that exists: whether it is a readable
    scan is for :func:`read_scan`, and a damaged one fails alone."""
    return (path.is_dir() and (path / "zarr.json").exists()) or (path.name.endswith(SCAN_SUFFIX) and path.exists())


def _import_hint(paths: list[str]) -> str:
    """A pointer to ``import-scan`` where ``paths`` hold files it reads; nothing otherwise."""
    from mpi_lidar.scans.importers import IMPORT_SUFFIXES

    importable = [p for p in paths if Path(p).suffix.lower() in IMPORT_SUFFIXES]
    if not importable:
        return ""
    return f"; {Path(importable[0]).name} is another tool's file: convert it first with mpi-lidar import-scan"


def correct_archive(inputs: list[str], model_dir: str | Path, out_dir: str | Path,
                    options: CorrectionOptions | None = None, executor: Executor | Client | None = None,
                    on_scan: Callable[[ScanOutcome], None] | None = None, *, client: Client | None = None,
                    outputs: str = "full", point_clouds: tuple[str, ...] | list[str] | None = None,
                    on_done: Callable[[list[ScanOutcome]], object] | None = None) -> list[ScanOutcome]:
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
    None: ply and las at level full, none below. ``options`` None: the defaults. ``on_done`` sees the outcomes
    while the batch still holds ``out_dir`` (:func:`output_lock`): the place for its summary.
    """
    options = options or CorrectionOptions()
    level = check_outputs(outputs)
    point_clouds = None if point_clouds is None else point_cloud_formats(level, point_clouds)
    _cached_model(str(model_dir))  # a broken model fails the whole batch at once, with one clear line
    make_gate(options)
    out_dir = Path(out_dir)
    sources = expand_archive(inputs)
    directories = scan_output_paths(sources)
    try:
        out_dir.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise MpiLidarError(f"cannot create output directory {out_dir}: {exc.strerror or exc}") from None
    with output_lock(out_dir):  # a second batch into out_dir is refused while this one runs
        for folder in sorted({PurePosixPath(output).parent for output in directories.values()}):
            if ".." not in folder.parts:
                remove_interrupted_staging(out_dir.joinpath(*folder.parts))
        calls = [{"source": source, "model_dir": str(model_dir), "out_dir": str(out_dir), "options": options,
                  "output": directories[source], "outputs": level, "point_clouds": point_clouds}
                 for source in sources]
        outcomes: list[ScanOutcome] = []
        for _call, outcome in as_executor(executor if executor is not None else client).map(process_scan, calls):
            outcomes.append(outcome)
            if on_scan:
                on_scan(outcome)
        outcomes.sort(key=lambda o: o.source)
        if on_done:  # the batch summary, written while the output directory is still this batch's
            on_done(outcomes)
    return outcomes


# --- one batch per output directory -----------------------------------------------------------------------

_held: dict[tuple[str, int], int] = {}  # (real path, thread) -> depth of nesting, of the holds of this process
_held_lock = threading.Lock()


@contextmanager
def output_lock(out_dir: str | Path) -> Iterator[None]:
    """Hold ``out_dir`` for one batch: a second batch (another process) into it is refused with one line.

    The lock is an exclusive ``flock`` on ``<out_dir>/.mpi-lidar-correct.lock``, which names the holder (process,
    host, start); the kernel releases it when the holder ends, even killed, so a lock is never stale.
    The file is removed when the batch ends (a run that was killed leaves it, and the next run takes it over).
    Nested holds in one thread (a command around :func:`correct_archive` and its batch summary) are one hold;
    a batch in another thread of the same process is refused like one in another process.
    Works where the file system supports ``flock`` across its clients (local disks; NFSv4 on Linux).
    """
    key = (os.path.realpath(out_dir), threading.get_ident())
    with _held_lock:
        if key in _held:
            _held[key] += 1
            nested = True
        else:
            nested = False
    if nested:
        try:
            yield
        finally:
            with _held_lock:
                _held[key] -= 1
        return
    path = Path(out_dir) / LOCK_FILE
    descriptor = _take_lock(path, Path(out_dir))
    with _held_lock:
        _held[key] = 1
    try:
        yield
    finally:
        with _held_lock:
            del _held[key]
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


# --- which outcomes fail a batch --------------------------------------------------------------------------

# The statuses --fail-on / fail_on may name; failed always fails, unserved unless allowed.
FAIL_ON = (ScanStatus.DEGRADED, ScanStatus.UNCHANGED, ScanStatus.FAILED)


def failing_outcomes(outcomes: list[ScanOutcome], fail_on: Sequence[str] = (),
                     allow_unserved: bool = False) -> list[ScanOutcome]:
    """The outcomes that fail the batch: every failed scan, every unserved one unless ``allow_unserved``, and
    those whose status is in ``fail_on``.

    A skipped scan counts with the status its existing outputs earned (:attr:`ScanOutcome.effective_status`),
    so a re-run fails on a degraded scan as the first run did. Other names than :data:`FAIL_ON` are refused.
    """
    unknown = sorted(set(fail_on) - set(FAIL_ON))
    if unknown:
        raise MpiLidarError(f"fail_on takes {', '.join(FAIL_ON)}; not {', '.join(map(repr, unknown))}")
    statuses = {ScanStatus.FAILED, *(ScanStatus(status) for status in fail_on)}
    if not allow_unserved:
        statuses.add(ScanStatus.UNSERVED)
    return [o for o in outcomes if o.effective_status in statuses]


def failure_line(outcome: ScanOutcome) -> str:
    """``scan <source>: <why>``, one line, for an outcome that fails the batch."""
    return f"scan {outcome.source}: {_why(outcome)}"


def _why(outcome: ScanOutcome) -> str:
    if outcome.status == ScanStatus.FAILED:
        why = outcome.reason
    elif outcome.effective_status == ScanStatus.DEGRADED:
        why = f"degraded: {100 * invalid_share(outcome.counts):.1f} % of its pixels are invalid"
    elif outcome.effective_status == ScanStatus.UNSERVED:
        why = f"unserved ({outcome.unserved}): {outcome.reason}" if outcome.status != ScanStatus.SKIPPED else (
            f"unserved ({outcome.unserved})")
    else:
        why = f"{outcome.effective_status}: no pixel was corrected"
    if outcome.status == ScanStatus.SKIPPED:
        why += " (existing outputs, already corrected with this model and options)"
    return why


def batch_failure(outcomes: list[ScanOutcome], fail_on: Sequence[str] = (),
                  allow_unserved: bool = False) -> str | None:
    """One line saying why the batch fails (``2 of 5 scans failed or degraded (...)``), or None if it does not."""
    bad = failing_outcomes(outcomes, fail_on, allow_unserved)
    if not bad:
        return None
    statuses = " or ".join(dict.fromkeys(str(o.effective_status) for o in bad))
    return f"{len(bad)} of {len(outcomes)} scans {statuses} ({'; '.join(f'{o.source}: {_why(o)}' for o in bad)})"

