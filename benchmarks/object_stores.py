"""Correction throughput per kind of object store: local disk, S3, Azure Blob Storage and GCS, each from its local
server on 127.0.0.1.

Run: .venv/bin/python -m benchmarks.object_stores [--scans 20] [--repeats 4] [--small]

The same archive (``--scans`` copies of :mod:`benchmarks.object_storage`'s 256 x 256 render) is corrected from and
to the local disk, moto's S3 server, Azurite (Azure Blob Storage; ``make system-deps`` installs it) and
fake-gcs-server (GCS), in this process with one worker thread, outputs at the default level. Each storage runs
``--repeats`` times in alternating order after a one-scan warm-up; the fastest run counts. The servers share the
cores with the worker, so the figures bound the tool's own overhead per store, not what a cloud service gives.
Every store's outputs are compared with the local disk's (bit-identical but for provenance and times) and the run
fails if one differs.
"""

from __future__ import annotations

import argparse
import platform
import tempfile
import time
import uuid
from collections.abc import Iterator
from contextlib import ExitStack, contextmanager
from dataclasses import dataclass
from datetime import date
from pathlib import Path

from benchmarks.object_storage import BUCKET, DEFAULT_OUTPUTS, Plan, archive, differing_outputs, s3_server, table
from mpi_lidar.locations import location
from mpi_lidar.storage import objects
from mpi_lidar.workflows.correct_archive import correct_archive

LOCAL = "local disk"
CONTAINER = "archive"


@dataclass(frozen=True)
class Store:
    """One kind of storage: its name in the table and the root URL of its archive and outputs (None: local)."""

    name: str
    root: str | None

    def source(self, local_archive: Path) -> str:
        return str(local_archive) if self.root is None else f"{self.root}/archive"

    def output(self, work: Path, run: str) -> str:
        return str(work / f"out-{run}") if self.root is None else f"{self.root}/out-{run}"


STORES = (Store(LOCAL, None), Store("S3 (moto)", f"s3://{BUCKET}"), Store("Azure (Azurite)", f"az://{CONTAINER}"),
          Store("GCS (fake-gcs-server)", f"gs://{CONTAINER}"))


@contextmanager
def servers() -> Iterator[None]:
    """The three local servers running and the standard variables of each store's library pointing at them."""
    from tests.azurite_server import azure_environment, azurite_server
    from tests.gcs_server import gcs_environment, gcs_server

    with ExitStack() as stack:
        stack.enter_context(s3_server())
        stack.enter_context(azure_environment(stack.enter_context(azurite_server())))
        stack.enter_context(gcs_environment(stack.enter_context(gcs_server())))
        yield


def upload(local_archive: Path, store: Store) -> None:
    """The local archive copied under ``<root>/archive`` of a store (its bucket or container made first)."""
    assert store.root is not None
    where = location(store.root)
    fs = objects.filesystem(where)
    fs.mkdir(where.path)
    fs.put(str(local_archive) + "/", f"{where.path}/archive", recursive=True)


def corrected_in(store: Store, sources: list[str], model: Path, out: str) -> float:
    """Seconds to correct ``sources`` into ``out``; a failed scan ends the benchmark with its reason."""
    started = time.perf_counter()
    outcomes = correct_archive(sources, model, out, outputs=DEFAULT_OUTPUTS)
    wall = time.perf_counter() - started
    failed = [o for o in outcomes if o.status.value == "failed"]
    if failed:
        raise SystemExit(f"error: {store.name}: {len(failed)} scan(s) failed, first {failed[0].source}: "
                         f"{failed[0].reason}")
    return wall


def fastest_runs(local_archive: Path, model: Path, work: Path, repeats: int) -> dict[Store, tuple[float, str]]:
    """Per store, the fastest of ``repeats`` corrections of the whole archive (alternating the stores' order) and
    where its outputs are; a one-scan run per store first loads the model and opens the store."""
    first = sorted(local_archive.glob("*.scan.zarr"))[0].name
    for store in STORES:
        corrected_in(store, [f"{store.source(local_archive)}/{first}"], model, store.output(work, "warm-" + _run_id()))
    best: dict[Store, tuple[float, str]] = {}
    for repeat in range(repeats):
        for store in STORES if repeat % 2 == 0 else STORES[::-1]:
            out = store.output(work, _run_id())
            wall = corrected_in(store, [store.source(local_archive)], model, out)
            if store not in best or wall < best[store][0]:
                best[store] = (wall, out)
    return best


def differing_from_local(best: dict[Store, tuple[float, str]], work: Path) -> dict[str, list[str]]:
    """Per object store, the outputs that differ from the local disk's run (downloaded first)."""
    here = Path(best[STORES[0]][1])
    differing = {}
    for store in STORES[1:]:
        there = work / f"down-{_run_id()}"
        where = location(best[store][1])
        objects.filesystem(where).get(where.path + "/", str(there), recursive=True)
        differing[store.name] = differing_outputs(here, there)
    return differing


def _run_id() -> str:
    return uuid.uuid4().hex[:8]


def rows(best: dict[Store, tuple[float, str]], scans: int) -> list[tuple[object, ...]]:
    local_rate = scans / best[STORES[0]][0]
    return [(store.name, f"{wall:.1f}", f"{scans / wall:.2f}", f"{scans / wall / local_rate:.2f}")
            for store, (wall, _) in best.items()]


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scans", type=int, default=20, help="scans of 256 x 256 in the archive")
    parser.add_argument("--repeats", type=int, default=4, help="runs of each storage; the fastest counts")
    parser.add_argument("--small", action="store_true", help="three tiny scans, one run each (the test)")
    args = parser.parse_args(argv)
    plan = (Plan(scans=3, side=24, big_scans=0, repeats=1) if args.small
            else Plan(scans=args.scans, big_scans=0, repeats=args.repeats))
    with tempfile.TemporaryDirectory(prefix="mpi-lidar-object-stores-") as scratch:
        work = Path(scratch)
        from tests.model_factory import tiny_model

        model = work / "model"
        tiny_model(model, geometric=False, feature_set="raw")
        local_archive = archive(work, plan)
        with servers():
            for store in STORES[1:]:
                upload(local_archive, store)
            best = fastest_runs(local_archive, model, work, plan.repeats)
            differing = differing_from_local(best, work)
    print(f"Archive: {plan.scans} scans of {plan.side} x {plan.side}, one worker thread, fastest of {plan.repeats}; "
          f"{platform.machine()} {platform.system()}, Python {platform.python_version()}, {date.today()}\n")
    print(table(("storage", "wall s", "scans/s", "over local disk"), rows(best, plan.scans)))
    bad = {name: names for name, names in differing.items() if names}
    if bad:
        name, names = next(iter(bad.items()))
        raise SystemExit(f"error: {len(names)} output(s) from {name} differ from the local disk's, first {names[0]}")
    print("\nOutputs from every store bit-identical to the local disk's (but source and timing fields): yes")


if __name__ == "__main__":
    main()
