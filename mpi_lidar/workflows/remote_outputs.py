"""Outputs whose place is an object store: built on the local disk exactly as local outputs are, then published.

A scan's outputs (and the batch summary) are written into a temporary directory by the same code that writes
them to a local ``--out``, so their bytes are those of a local run; the directory is then uploaded below its
place and published by its manifest, written last by a conditional create
(:func:`mpi_lidar.storage.objects.publish_directory`, whose docstring states the guarantees). Files shared by
the batch beside the scans' folders (``plotly.min.js`` of the full level) are uploaded once, where absent.
"""

from __future__ import annotations

import dataclasses
import tempfile
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from pathlib import Path

from mpi_lidar.correction import ScanOutcome
from mpi_lidar.locations import Location, location
from mpi_lidar.reporting.batch_report import write_batch_report
from mpi_lidar.storage.objects import exists, publish_directory, publish_store, write_object


@contextmanager
def written_at(target: Path | Location, bundle_dir: Path | Location | None, output: str
               ) -> Iterator[tuple[Path, Path | None]]:
    """(directory to write a scan's outputs into, its bundle folder); a local target is both as given, a
    target in a store a temporary directory laid out like ``<out>/``, published when the block ends without
    an exception (and removed either way). ``output`` is the scan's folder relative to ``<out>``."""
    if isinstance(target, Path):
        yield target, bundle_dir if isinstance(bundle_dir, Path) or bundle_dir is None else None
        return
    with tempfile.TemporaryDirectory(prefix="mpi-lidar-outputs-") as temporary:
        root = Path(temporary)
        directory = root.joinpath(*(output or target.name).split("/"))
        yield directory, root
        publish_directory(directory, target)
        if isinstance(bundle_dir, Location):
            for shared in sorted(p for p in root.iterdir() if p.is_file()):
                if not exists(bundle_dir.joinpath(shared.name)):
                    write_object(bundle_dir.joinpath(shared.name), shared.read_bytes())


def write_summary(outcomes: list[ScanOutcome], wall_s: float, out_dir: str | Path | Location) -> str:
    """The batch summary into ``<out_dir>/summary/`` (a path or a store); where it is, for the terminal.

    In a store it is written in a temporary ``<out>/`` first, the outcomes' output folders seen from there
    (an empty stand-in for each report published), so its links to the scans' reports are those of a local
    summary."""
    out = location(out_dir)
    if out.is_local:
        return str(write_batch_report(outcomes, wall_s, out.local_path()))
    prefix = out.url.rstrip("/") + "/"
    with tempfile.TemporaryDirectory(prefix="mpi-lidar-summary-") as temporary:
        root = Path(temporary)
        seen = [dataclasses.replace(o, output=str(root / o.output.removeprefix(prefix)))
                if o.output.startswith(prefix) else o for o in outcomes]
        for there, here in zip(outcomes, seen, strict=True):  # the summary links the reports that exist
            if there.output.startswith(prefix) and exists(location(there.output).joinpath("report.html")):
                (Path(here.output) / "report.html").parent.mkdir(parents=True, exist_ok=True)
                (Path(here.output) / "report.html").touch()
        summary = write_batch_report(seen, wall_s, root)
        publish_directory(summary, out.joinpath(summary.name))
    return str(out.joinpath(summary.name))


ImportPlan = list[tuple[Path, Path]]


def import_into_store(files: Sequence[Path], out: Location, run: Callable[[ImportPlan], object]
                      ) -> tuple[list[tuple[Path, Location]], list[tuple[Path, Location]]]:
    """Import ``files`` into scan stores below (or at) ``out`` in an object store: (imported, already there),
    each (source, store).

    The stores are written by ``run`` (:func:`mpi_lidar.scans.importers.import_files` of the plan: every file
    read and checked first, all stores or none) into a temporary directory laid out as ``out``, then each is
    published (:func:`~mpi_lidar.storage.objects.publish_store`: its root metadata last, by a conditional create).
    A store already in the bucket is not written again; where all are, the import is refused with one line.
    """
    from mpi_lidar.scans.importers import plan_import
    from mpi_lidar.scans.scan import ScanError

    with tempfile.TemporaryDirectory(prefix="mpi-lidar-import-") as temporary:
        local_out = Path(temporary) / out.name
        plan = plan_import(files, local_out)
        there = {target: out if target == local_out else out.joinpath(target.name) for _, target in plan}
        existing = [(source, target) for source, target in plan if exists(there[target].joinpath("zarr.json"))]
        if existing and len(existing) == len(plan):
            raise ScanError(f"{there[existing[0][1]]} already exists, so {existing[0][0]} was not imported; nothing "
                            "was new: remove a store to import its file again, or choose another --out")
        todo = [pair for pair in plan if pair not in existing]
        run(todo)
        for _, target in todo:
            publish_store(target, there[target])
    return [(s, there[t]) for s, t in todo], [(s, there[t]) for s, t in existing]
