"""Object-storage throughput: an archive corrected from and to a local S3 server, against the same on local disk.

Run: .venv/bin/python -m benchmarks.object_storage [--scans 200] [--side 256] [--big-scans 10] [--big-side 1000]
     [--workers 1,2] [--model DIR] [--work DIR] [--small]

The archive is ``--scans`` scans of ``--side`` x ``--side`` pixels and ``--big-scans`` of ``--big-side`` x
``--big-side`` (the cornered board, each rendered once and stored under as many names; 4 frequencies), once on
the local disk and once in a bucket of moto's S3 server, started here as its own process on 127.0.0.1. Each is
corrected by :func:`~mpi_lidar.workflows.correct_archive.correct_archive` with the command line's default
outputs on a LocalCluster of 1 and of 2 Dask worker processes (one thread each): from the disk into a local
folder, and from the bucket into the bucket, every worker reading and publishing its own scans. Wall times
exclude starting the cluster and the workers' first imports and model load (a run of one scan of each size
first); each storage runs ``--repeats`` times per cluster, in alternating order, and the fastest run counts
(the machine may be shared).

Per run: scans per second; MB read and written per scan (from and to the bucket: the bodies of the S3 requests;
on disk: the bytes zarr read from the scan stores, and the size of the outputs written); S3 requests per scan
(LIST, HEAD, GET, PUT, DELETE, answered or refused: a 404 is a request too, counted in every process); and the
share of the workers' time spent waiting on storage (the union of the intervals inside S3 requests and zarr's
local reads and writes, per process, over workers x wall). The outputs corrected from the bucket are then
compared with those from the disk: every file must be bit-identical but those that name their source or the
seconds taken (reports, metrics, manifests, the corrected store's attributes, the summary); the run fails
otherwise.

The S3 server is a local process sharing the cores with the workers: its figures are what this machine gives,
a planning figure, not a gate. ``--small``: four tiny scans, one worker thread in this process (workers
0), for the test.
"""

from __future__ import annotations

import argparse
import logging
import os
import shutil
import socket
import subprocess
import sys
import tempfile
import threading
import time
import uuid
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path

from mpi_lidar.locations import location
from mpi_lidar.reporting.output_levels import DEFAULT_OUTPUTS
from mpi_lidar.storage import objects
from mpi_lidar.storage.manifest import MANIFEST_FILE
from mpi_lidar.workflows.cluster import dask_client
from mpi_lidar.workflows.correct_archive import correct_archive

BUCKET = "benchmark"
# Outputs that name where they came from or the seconds taken: the only files that may differ from disk's.
AWS_VARIABLES = ("AWS_ENDPOINT_URL", "AWS_ACCESS_KEY_ID", "AWS_SECRET_ACCESS_KEY", "AWS_DEFAULT_REGION")
PROVENANCE = ("report.md", "report.html", "metrics.json", MANIFEST_FILE, "corrected.zarr/zarr.json")
# The S3 operations the tool asks for, by the table's column: DELETE counts single and bulk deletions.
COLUMNS = {"LIST": ("ListObjectsV2",), "HEAD": ("HeadObject",), "GET": ("GetObject",), "PUT": ("PutObject",),
           "DELETE": ("DeleteObject", "DeleteObjects")}
OPERATIONS = tuple(op for ops in COLUMNS.values() for op in ops)


# --- counting what each process asks of its stores ------------------------------------------------------------

_counts: dict[str, float] = {}
_intervals: list[tuple[float, float]] = []
_counting = threading.Lock()


def _record(name: str, started: float, size: int = 0) -> None:
    with _counting:
        _counts[name] = _counts.get(name, 0) + 1
        _counts[name + " bytes"] = _counts.get(name + " bytes", 0) + size
        _intervals.append((started, time.perf_counter()))


def install_counters() -> None:
    """Count every S3 request (aiobotocore, which s3fs and zarr's FsspecStore use), answered or refused, and every
    zarr read and write of a local store in this process, with the bytes and the time inside them (idempotent)."""
    from aiobotocore.client import AioBaseClient
    from zarr.storage import LocalStore

    if getattr(AioBaseClient, "_counted", False):
        return
    make_call, get, set_ = AioBaseClient._make_api_call, LocalStore.get, LocalStore.set

    async def counted_call(self, operation_name, api_params):
        started = time.perf_counter()
        sent = _body_bytes(api_params.get("Body"))  # before the call, which wraps the body to checksum it
        received = 0
        try:
            response = await make_call(self, operation_name, api_params)
            received = int(response.get("ContentLength") or 0) if operation_name == "GetObject" else 0
            return response
        finally:  # a refused request (a missing key's 404, a failed conditional create) is a request too
            _record(operation_name, started, sent + received)

    async def counted_get(self, key, *args, **kwargs):  # zarr's own signature passed on, defaults included
        started = time.perf_counter()
        buffer = await get(self, key, *args, **kwargs)
        _record("local read", started, 0 if buffer is None else len(buffer))
        return buffer

    async def counted_set(self, key, value, *args, **kwargs):
        started = time.perf_counter()
        await set_(self, key, value, *args, **kwargs)
        _record("local write", started, len(value))

    AioBaseClient._make_api_call, LocalStore.get, LocalStore.set = counted_call, counted_get, counted_set
    AioBaseClient._counted = True


def _body_bytes(body: object) -> int:
    """The size of a request's body: bytes, or an open file (s3fs uploads a file from its handle)."""
    if isinstance(body, bytes | bytearray | memoryview):
        return len(body)
    try:
        return os.fstat(body.fileno()).st_size  # type: ignore[union-attr]
    except (AttributeError, OSError, ValueError):
        return 0


def take_counters() -> dict[str, float]:
    """What this process counted since the last call (and the seconds inside storage, their union), then reset."""
    with _counting:
        counts, intervals = dict(_counts), sorted(_intervals)
        _counts.clear()
        _intervals.clear()
    busy, end = 0.0, float("-inf")
    for start, stop in intervals:
        if stop > end:
            busy += stop - max(start, end)
            end = stop
    counts["storage s"] = busy
    return counts


def cluster_counters(client) -> dict[str, float]:
    """The counters of this process and of every worker, summed."""
    total = take_counters()
    for counts in client.run(take_counters).values():
        for key, value in counts.items():
            total[key] = total.get(key, 0) + value
    return total


# --- the S3 server ----------------------------------------------------------------------------------------------


@contextmanager
def s3_server() -> Iterator[str]:
    """moto's S3 server as its own process on a free port of 127.0.0.1, and the standard AWS variables pointing at
    it (the workers started afterwards inherit them); its endpoint."""
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        port = probe.getsockname()[1]
    server = subprocess.Popen([sys.executable, "-m", "moto.server", "-H", "127.0.0.1", "-p", str(port)],
                              stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, start_new_session=True)
    endpoint = f"http://127.0.0.1:{port}"
    try:
        deadline = time.monotonic() + 30
        while True:
            try:
                socket.create_connection(("127.0.0.1", port), timeout=1).close()
                break
            except OSError:
                if time.monotonic() > deadline or server.poll() is not None:
                    raise RuntimeError("moto's S3 server did not start") from None
                time.sleep(0.1)
        with aws_environment(endpoint, "benchmark", "benchmark"):
            yield endpoint
    finally:
        server.terminate()
        server.wait(timeout=10)


@contextmanager
def aws_environment(endpoint: str, key_id: str, secret: str) -> Iterator[None]:
    """The standard AWS variables pointing at ``endpoint`` with these keys inside the block (processes started in
    it inherit them), and put back as they were after it."""
    from tests.environment import environment

    with environment(AWS_VARIABLES, {"AWS_ENDPOINT_URL": endpoint, "AWS_ACCESS_KEY_ID": key_id,
                                     "AWS_SECRET_ACCESS_KEY": secret, "AWS_DEFAULT_REGION": "us-east-1"},
                     forget_s3_clients):
        yield


def forget_s3_clients() -> None:
    """Drop this process's cached S3 file systems: each read the endpoint and keys from the environment when it
    was made, and fsspec hands the same one back for the same options, so a changed environment needs new ones."""
    from s3fs import S3FileSystem

    S3FileSystem.clear_instance_cache()


# --- the archive ------------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Plan:
    scans: int = 200
    side: int = 256
    big_scans: int = 10
    big_side: int = 1000
    workers: tuple[int, ...] = (1, 2)
    train_rows: int = 50_000
    rounds: int = 200
    repeats: int = 2

    @classmethod
    def small(cls) -> Plan:
        return cls(scans=3, side=24, big_scans=1, big_side=48, workers=(0,), train_rows=2_000, rounds=10,
                   repeats=1)


def archive(work: Path, plan: Plan) -> Path:
    """The local archive: ``plan.scans`` copies of the small render and ``plan.big_scans`` of the big one, each
    under its own name (reused when there)."""
    from benchmarks.correction import rendered

    folder = work / f"archive-{plan.scans}x{plan.side}-{plan.big_scans}x{plan.big_side}"
    if folder.is_dir():
        return folder
    staging = Path(tempfile.mkdtemp(dir=work))
    for count, side, prefix in ((plan.scans, plan.side, "s"), (plan.big_scans, plan.big_side, "b")):
        if count == 0:
            continue
        source = rendered(work, side)
        for index in range(count):
            shutil.copytree(source, staging / f"{prefix}{index:04d}.scan.zarr")
    staging.rename(folder)
    return folder


def tree_bytes(folder: Path) -> int:
    return sum(p.stat().st_size for p in folder.rglob("*") if p.is_file())


def files_of(folder: Path) -> dict[str, bytes]:
    return {p.relative_to(folder).as_posix(): p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file()}


def differing_outputs(local: Path, from_bucket: Path) -> list[str]:
    """The outputs that are not bit-identical between a local run and a run in the bucket (downloaded), but for
    those that name their source or the time taken (:data:`PROVENANCE`, the summary); the local folder's lock file
    aside. Empty where the outputs agree."""
    here = {n: v for n, v in files_of(local).items() if not n.startswith(".mpi-lidar-correct.lock")}
    there = files_of(from_bucket)
    missing = sorted(set(here) ^ set(there))
    differing = [n for n in sorted(here.keys() & there.keys()) if here[n] != there[n]
                 and not n.startswith("summary/") and n.split("/", 1)[-1] not in PROVENANCE]
    return missing + differing


# --- the runs ---------------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Run:
    storage: str
    workers: int
    scans: int
    wall_s: float
    counts: dict[str, float]
    written_bytes: int

    def row(self) -> tuple[object, ...]:
        per = 1 / self.scans
        s3 = self.storage == "S3"
        read = self.counts.get("GetObject bytes", 0) if s3 else self.counts.get("local read bytes", 0)
        written = self.counts.get("PutObject bytes", 0) if s3 else self.written_bytes
        requests = [f"{sum(self.counts.get(op, 0) for op in ops) * per:.1f}" if s3 else "-"
                    for ops in COLUMNS.values()]
        share = self.counts.get("storage s", 0) / (max(self.workers, 1) * self.wall_s)
        return (self.storage, self.workers, self.scans, f"{self.wall_s:.1f}", f"{self.scans / self.wall_s:.2f}",
                f"{read * per / 1e6:.2f}", f"{written * per / 1e6:.2f}", *requests, f"{100 * share:.0f} %")


def corrected(client, sources: str, model: Path, out: str, warm: str, warm_out: str) -> tuple[float, dict]:
    """Seconds to correct the archive at ``sources`` into ``out`` on the client's workers, and what was counted;
    a one-scan run into ``warm_out`` first loads the model and opens the stores on every worker."""
    correct_archive([warm], model, warm_out, client=client, outputs=DEFAULT_OUTPUTS)
    client.run(install_counters)
    cluster_counters(client)
    started = time.perf_counter()
    outcomes = correct_archive([sources], model, out, client=client, outputs=DEFAULT_OUTPUTS)
    wall = time.perf_counter() - started
    failed = [o for o in outcomes if o.status.value == "failed"]
    if failed:
        raise SystemExit(f"error: {len(failed)} scan(s) failed, first {failed[0].source}: {failed[0].reason}")
    return wall, cluster_counters(client)


def warm_archive(work: Path, local: Path) -> Path:
    """One scan of each size, for the runs that load the model and open the stores before the timed ones."""
    warm = work / f"warm-{local.name}"
    if not warm.is_dir():
        warm.mkdir()
        for prefix in ("s", "b"):
            first = next(local.glob(f"{prefix}*.scan.zarr"), None)
            if first is not None:
                shutil.copytree(first, warm / f"warm-{first.name}")
    return warm


def measure(plan: Plan, work: Path, model: Path) -> tuple[list[Run], list[str]]:
    """Every run of the plan; per worker count, the fastest of ``plan.repeats`` runs of each storage (their order
    alternating, so that neither always runs first), and the outputs that differ between the two storages."""
    local = archive(work, plan)
    warm = warm_archive(work, local)
    scans = plan.scans + plan.big_scans
    runs: list[Run] = []
    differing: list[str] = []
    install_counters()
    with s3_server():
        fs = objects.filesystem(location(f"s3://{BUCKET}"))
        fs.mkdir(BUCKET)
        fs.put(str(local) + "/", f"{BUCKET}/archive", recursive=True)
        fs.put(str(warm) + "/", f"{BUCKET}/warm", recursive=True)
        for workers in plan.workers:
            fastest: dict[str, Run] = {}
            with dask_client(None, workers) as client:
                for repeat in range(plan.repeats):
                    run_id = uuid.uuid4().hex[:8]
                    out_local, out_s3 = work / f"out-{run_id}", f"s3://{BUCKET}/out-{run_id}"
                    for storage in ("local disk", "S3")[::1 if repeat % 2 == 0 else -1]:
                        if storage == "S3":
                            wall, counts = corrected(client, f"s3://{BUCKET}/archive", model, out_s3,
                                                     f"s3://{BUCKET}/warm", f"s3://{BUCKET}/warm-out-{run_id}")
                        else:
                            wall, counts = corrected(client, str(local), model, str(out_local), str(warm),
                                                     str(work / f"warm-out-{run_id}"))
                        run = Run(storage, workers, scans, wall, counts, tree_bytes(out_local) if storage != "S3"
                                  else 0)
                        if storage not in fastest or run.wall_s < fastest[storage].wall_s:
                            fastest[storage] = run
                    differing += compared(fs, work, out_local, run_id)
            runs += [fastest["local disk"], fastest["S3"]]
    return runs, differing


def compared(fs, work: Path, out_local: Path, run_id: str) -> list[str]:
    """The outputs of one repeat that differ between disk and bucket (:func:`differing_outputs`); both removed."""
    downloaded = work / f"downloaded-{run_id}"
    fs.get(f"{BUCKET}/out-{run_id}/", str(downloaded), recursive=True)
    try:
        return differing_outputs(out_local, downloaded)
    finally:
        shutil.rmtree(out_local)
        shutil.rmtree(downloaded)
        shutil.rmtree(work / f"warm-out-{run_id}", ignore_errors=True)


def table(headers: tuple[str, ...], rows: list[tuple[object, ...]]) -> str:
    lines = ["| " + " | ".join(headers) + " |", "|" + "---|" * len(headers)]
    return "\n".join(lines + ["| " + " | ".join(str(c) for c in row) + " |" for row in rows])


HEADERS = ("storage", "workers", "scans", "wall s", "scans/s", "MB read/scan", "MB written/scan",
           *(f"{column}/scan" for column in COLUMNS), "time in storage")


def ratios(runs: list[Run]) -> list[tuple[object, ...]]:
    """Per worker count: S3's throughput over the local disk's, measured in the same cluster."""
    rate = {(r.storage, r.workers): r.scans / r.wall_s for r in runs}
    return [(w, f"{rate['S3', w] / rate['local disk', w]:.2f}")
            for w in sorted({r.workers for r in runs}) if ("S3", w) in rate and ("local disk", w) in rate]


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scans", type=int, default=Plan.scans)
    parser.add_argument("--side", type=int, default=Plan.side)
    parser.add_argument("--big-scans", type=int, default=Plan.big_scans)
    parser.add_argument("--big-side", type=int, default=Plan.big_side)
    parser.add_argument("--workers", default="1,2", help="worker counts, comma-separated")
    parser.add_argument("--repeats", type=int, default=Plan.repeats, help="runs of each storage; the fastest counts")
    parser.add_argument("--model", type=Path, help="a model directory (default: one trained here)")
    parser.add_argument("--work", type=Path, help="where renders, the model and outputs are kept")
    parser.add_argument("--small", action="store_true", help="four tiny scans, in this process (the test)")
    args = parser.parse_args(argv)
    plan = Plan.small() if args.small else Plan(args.scans, args.side, args.big_scans, args.big_side,
                                                tuple(int(w) for w in args.workers.split(",")),
                                                repeats=args.repeats)
    logging.getLogger("distributed").setLevel(logging.ERROR)
    work = args.work or Path(tempfile.gettempdir()) / f"mpi-lidar-object-storage-{os.getuid()}"
    work.mkdir(parents=True, exist_ok=True)
    from benchmarks.correction import trained_model

    model = args.model or trained_model(work / f"model-{plan.train_rows}-{plan.rounds}", plan.train_rows,
                                        plan.rounds)
    runs, differing = measure(plan, work, model)
    print(f"Archive: {plan.scans} scans of {plan.side} x {plan.side} and {plan.big_scans} of {plan.big_side} x "
          f"{plan.big_side}; outputs at the default level (light).\n")
    print(table(HEADERS, [run.row() for run in runs]))
    print("\n" + table(("workers", "S3 scans/s over local disk scans/s"), ratios(runs)))
    if differing:
        raise SystemExit(f"error: {len(differing)} output(s) from the bucket differ from the local disk's, first "
                         f"{differing[0]}")
    print("\nOutputs from the bucket bit-identical to the local disk's (but source and timing fields): yes")


if __name__ == "__main__":
    # Run as the importable module, not as __main__: the workers import its counters by that name.
    from benchmarks.object_storage import main as importable_main

    importable_main()
