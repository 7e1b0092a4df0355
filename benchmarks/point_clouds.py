"""What the point-cloud files of a corrected scan cost beside the scan's correction.

Run: .venv/bin/python -m benchmarks.point_clouds [--model DIR] [--work DIR] [--side 1000] [--train-rows N]
     [--repeats 3] [--quick]
One markdown table: a ``--side`` x ``--side`` render of the cornered board (4 frequencies, Table I noise,
geometry gate, the model loaded and caches warm, as for every scan of a batch but the first), and

- its correction: :func:`~mpi_lidar.workflows.correct_archive.process_scan` from the store to the written
  outputs at the light level (without point clouds), and :func:`~mpi_lidar.correction.correct_scan` alone;
- each point-cloud format written by :func:`~mpi_lidar.reporting.point_cloud_files.write_point_clouds` from
  the corrected scan (fields, colours, points and the file): wall and CPU seconds, the file's size, and its
  wall and CPU time as shares of ``process_scan``'s. The target (a LAZ at the default output level) is a LAZ
  that costs at most 20 % of the correction, by both measures;
- for comparison, the LAZ as the writer built it before (every field through laspy's per-dimension setters).

Each time is the fastest of ``--repeats`` rounds, each round measuring everything once, in turn (a shared
machine's load then weighs on each alike). On a shared machine, run it with ``OMP_NUM_THREADS=1``: every
stage then runs on one thread (:func:`mpi_lidar.threads.cores`), whose CPU seconds are not inflated by
threads that wait for a core, and the CPU share is the figure to quote. The model is ``--model DIR``, or the
correction benchmark's (trained here with default parameters on ``--train-rows`` rows, kept in ``--work``,
by default the correction benchmark's directory, so that both measure the same model and scan).
"""

from __future__ import annotations

import argparse
import os
import platform
import shutil
import tempfile
import time
from collections.abc import Callable
from dataclasses import dataclass
from datetime import date
from pathlib import Path

import numpy as np

from benchmarks.correction import rendered, table, trained_model
from mpi_lidar.correction import CorrectionOptions, correct_scan
from mpi_lidar.learning.model import load_model
from mpi_lidar.learning.train import DEFAULT_ROUNDS
from mpi_lidar.reporting.metrics import measured_depth
from mpi_lidar.reporting.point_cloud_files import write_point_clouds
from mpi_lidar.scans.pointcloud import LAS_SCALE_M, PointCloudFormat, correction_fields
from mpi_lidar.scans.store import read_scan
from mpi_lidar.workflows.correct_archive import process_scan

HEADERS = ("run", "points", "wall s", "CPU s", "file MB", "share of the correction, wall", "share, CPU", "target",
           "met")
TARGET_SHARE = 0.20


@dataclass(frozen=True)
class Plan:
    """Sizes of one run."""

    side: int = 1000
    train_rows: int = 50_000
    rounds: int = DEFAULT_ROUNDS
    repeats: int = 3

    @classmethod
    def quick(cls) -> Plan:
        return cls(side=48, train_rows=2_000, rounds=10, repeats=1)


def fastest(work: Callable[[], object], repeats: int) -> tuple[float, float]:
    """The wall and CPU seconds of the fastest of ``repeats`` calls of ``work``."""
    runs = []
    for _ in range(repeats):
        cpu, wall = time.process_time(), time.perf_counter()
        work()
        runs.append((time.perf_counter() - wall, time.process_time() - cpu))
    return min(runs)


def laz_before(path: Path, points: np.ndarray, fields: dict[str, np.ndarray]) -> None:
    """The LAZ as the writer built it before: finite points only, each field set through laspy's setters."""
    import laspy

    keep = np.isfinite(points).all(axis=-1).reshape(-1)
    xyz = points.reshape(-1, 3)[keep]
    rows, columns = np.divmod(np.flatnonzero(keep).astype(np.uint32), np.uint32(points.shape[1]))
    values = {name: v.reshape(-1)[keep] for name, v in fields.items()} | {"row": rows, "column": columns}
    header = laspy.LasHeader(version="1.4", point_format=6)
    header.scales = np.full(3, LAS_SCALE_M)
    header.offsets = np.floor(xyz.min(axis=0))
    header.add_extra_dims([laspy.ExtraBytesParams(name=name, type=v.dtype) for name, v in values.items()])
    las = laspy.LasData(header)
    las.x, las.y, las.z = xyz[:, 0], xyz[:, 1], xyz[:, 2]
    for name, v in values.items():
        las[name] = v
    with path.open("wb") as stream:
        las.write(stream, do_compress=True, laz_backend=laspy.LazBackend.Lazrs)


def run(plan: Plan, model_dir: Path | None, work: Path) -> str:
    """The table of one run, as markdown, after a line naming the machine."""
    work.mkdir(parents=True, exist_ok=True)
    load = ", ".join(f"{x:.1f}" for x in os.getloadavg())
    head = (f"Machine: {platform.node()} ({platform.machine()}), {os.cpu_count()} cores, Python "
            f"{platform.python_version()}, {date.today()}; load average {load} at the start")
    print(head, flush=True)
    model_dir = model_dir or trained_model(work / f"model-{plan.train_rows}-{plan.rounds}", plan.train_rows,
                                           plan.rounds)
    source = rendered(work, plan.side)
    options = CorrectionOptions()
    out = work / "point-clouds-out"
    shutil.rmtree(out, ignore_errors=True)
    process_scan(source, model_dir, out / "warm", options, outputs="light", point_clouds=())  # model cached

    def correct_light() -> None:
        shutil.rmtree(out / "light", ignore_errors=True)
        outcome = process_scan(source, model_dir, out / "light", options, outputs="light", point_clouds=())
        if outcome.status == "failed":
            raise SystemExit(f"correction failed: {outcome.reason}")

    model, scan = load_model(model_dir), read_scan(source)
    correct_scan(scan, model, options)
    correction = correct_scan(scan, model, options)
    rays = scan.rays()
    if rays is None:
        raise SystemExit(f"{source}: the scan has no geometry")
    measured = measured_depth(scan, correction)
    amplitude = np.asarray(scan.amplitude[-1])
    written = out / "files"
    written.mkdir()
    names: dict[PointCloudFormat, list[str]] = {}

    def writer(fmt: PointCloudFormat) -> Callable[[], object]:
        def write() -> None:
            names[fmt] = write_point_clouds(written, (fmt,), rays, scan, correction)
        return write

    fields = correction_fields(measured, correction.depth, correction.flags, amplitude)
    corrected_points = rays * correction.depth[..., None].astype(np.float64)
    works: dict[str, Callable[[], object]] = {
        "correction": correct_light, "correct_scan": lambda: correct_scan(scan, model, options),
        **{fmt.value: writer(fmt) for fmt in (PointCloudFormat.LAZ, PointCloudFormat.LAS, PointCloudFormat.PLY)},
        "before": lambda: laz_before(written / "before.laz", corrected_points, fields),
    }
    works["laz"]()  # warm: laspy is imported on the first LAS file
    # Interleaved, one round of every measurement at a time: a shared machine's load then weighs on each alike.
    best: dict[str, tuple[float, float]] = {}
    for _ in range(plan.repeats):
        for name, work_ in works.items():
            timed = fastest(work_, 1)
            best[name] = min(best.get(name, timed), timed)
    process_wall, process_cpu = best["correction"]
    pixels = scan.shape[0] * scan.shape[1]

    def shares(name: str) -> tuple[str, str]:
        wall, cpu = best[name]
        return f"{100 * wall / process_wall:.0f} %", f"{100 * cpu / process_cpu:.0f} %"

    rows: list[tuple[object, ...]] = [
        ("process_scan, outputs light, no point clouds (the correction)", f"{pixels:,}", f"{process_wall:.2f}",
         f"{process_cpu:.2f}", "", "100 %", "100 %", "", ""),
        ("correct_scan alone", f"{pixels:,}", f"{best['correct_scan'][0]:.2f}", f"{best['correct_scan'][1]:.2f}", "",
         *shares("correct_scan"), "", ""),
    ]
    for fmt in (PointCloudFormat.LAZ, PointCloudFormat.LAS, PointCloudFormat.PLY):
        wall, cpu = best[fmt.value]
        size = sum((written / name).stat().st_size for name in names[fmt]) / 1e6
        share = max(wall / process_wall, cpu / process_cpu)
        target = fmt == PointCloudFormat.LAZ
        points = (np.isfinite(measured).sum() if fmt != PointCloudFormat.PLY
                  else 2 * np.isfinite(correction.depth).sum())
        rows.append((f"write_point_clouds {fmt.value} ({', '.join(names[fmt])})", f"{points:,}", f"{wall:.2f}",
                     f"{cpu:.2f}", f"{size:.2f}", *shares(fmt.value),
                     f"<= {100 * TARGET_SHARE:.0f} %" if target else "",
                     ("yes" if share <= TARGET_SHARE else "no") if target else ""))
    wall, cpu = best["before"]
    rows.append(("LAZ as written before (laspy setters, valid points only)",
                 f"{np.isfinite(correction.depth).sum():,}", f"{wall:.2f}", f"{cpu:.2f}",
                 f"{(written / 'before.laz').stat().st_size / 1e6:.2f}", *shares("before"), "", ""))
    text = table(HEADERS, rows)
    print("\n" + text, flush=True)
    return head + "\n\n" + text


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--model", type=Path, help="Model directory (default: train one here).")
    parser.add_argument("--work", type=Path, help="Directory for the render, the model and outputs (kept).")
    parser.add_argument("--side", type=int, help="Side of the scan [px] (default 1000).")
    parser.add_argument("--train-rows", type=int, help="Rows the model is trained on (default 50,000).")
    parser.add_argument("--repeats", type=int, help="Runs per measurement, the fastest kept (default 3).")
    parser.add_argument("--quick", action="store_true", help="Tiny sizes (seconds): for a first look and tests.")
    args = parser.parse_args(argv)
    plan = Plan.quick() if args.quick else Plan()
    sizes = {"side": args.side, "train_rows": args.train_rows, "repeats": args.repeats}
    plan = Plan(**{**plan.__dict__, **{k: v for k, v in sizes.items() if v is not None}})
    work = args.work or Path(tempfile.gettempdir()) / "mpi-lidar-bench-correction"
    run(plan, args.model, work)


if __name__ == "__main__":
    main()
