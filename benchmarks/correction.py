"""Where the time of archive correction goes: per stage, end to end, per scan in a batch, and peak memory.

Run: .venv/bin/python -m benchmarks.correction [--model DIR] [--work DIR] [--side 1000] [--batch 200]
     [--batch-side 256] [--big-side 4000] [--quick] [--only memory|startup]
One run prints six tables, each a markdown table (``--quick``: tiny sizes, seconds, for the test; ``--only``:
table 5 or table 6 alone, as the other tables' minutes do not change a peak or a start-up):

1. Stages of one ``--side`` x ``--side`` render of the cornered board (4 frequencies, Table I noise,
   geometry gate, this process, caches warm): CPU seconds of this process (all threads, so robust when other
   jobs share the machine) and CPU seconds per megapixel of read, unit, validity, gate, features, inference,
   baseline, write and figures. Features and inference are one call in ``correct_scan``; they are told apart by
   building the same pixels' features again alone. Write and figures are given per output level (data, light, full).
2. End to end, :func:`~mpi_lidar.workflows.correct_archive.process_scan` from the store to the written
   outputs, per output level (warm: model loaded, as for every scan of a batch but the first; the fastest
   of three runs, as the machine may be shared), and the
   command line (``mpi-lidar correct SCAN --model M --out O``, default options: imports, model and one scan
   included): wall seconds and pixels per second.
3. Pure XGBoost: ``inplace_predict`` of the same model on the features of all the scan's pixels, and the
   ratio of the end-to-end time (default outputs) to it.
4. A batch of ``--batch`` scans of ``--batch-side`` x ``--batch-side`` (one render stored under as many
   names) through :func:`~mpi_lidar.workflows.correct_archive.correct_archive` in this process with the
   default outputs: seconds per scan, and the overhead per scan beyond the pixel cost of table 2; once with
   the footprint measured on every scan (``auto``, the default) and once with it given, as a sensor profile
   (``mpi-lidar calibrate``) gives it.
5. Peak memory (peak resident set, VmHWM, of a fresh process that corrects one scan with the default
   outputs, and its growth over the same process after imports and model loading) for the ``--side`` scan and a
   ``--big-side`` one. The big scan is the ``--side`` render with every pixel repeated (big-side / side)^2
   times on a finer scan grid: sizes, not accuracy, matter there.
6. Start-up of a one-scan ``mpi-lidar correct`` (:mod:`benchmarks.startup`): what a fresh process pays before
   its scan's own work, at output levels data and light, against the goal of at most 0.7 s.

The model is ``--model DIR``, or one trained here (default parameters, early stopping) on ``--train-rows``
rows simulated from the default prior with the geometric inputs the scan geometry would give: the default
model's feature set and size. Renders and the model are kept in ``--work`` (default: a directory under
the system's temporary directory), so a second run starts at once. The targets of the last column come from
the archive-correction goal: >= 1,000,000 pixels/s end to end with the default outputs, <= 3x pure
inference, <= 0.2 s overhead per scan in a 200-scan batch, <= 1 GiB peak at 4000 x 4000.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import os
import platform
import resource
import shutil
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass, replace
from datetime import date
from pathlib import Path

import numpy as np

from benchmarks.startup import startup_tables
from mpi_lidar.config import Config
from mpi_lidar.correction import MODEL_FLAGS, CorrectionOptions, correct_scan
from mpi_lidar.learning.features import DEFAULT_FEATURE_SET, DEFAULT_TARGET_MODE, FeatureSpec, synthetic_geometry
from mpi_lidar.learning.model import load_model, save_model
from mpi_lidar.learning.model_card import DatasetCard
from mpi_lidar.learning.train import DEFAULT_EARLY_STOPPING, DEFAULT_ROUNDS, model_card, train_arrays
from mpi_lidar.physics.coupling import DEFAULT_FOOTPRINT_AREA_M2
from mpi_lidar.reporting.metrics import scan_metrics
from mpi_lidar.reporting.output_levels import DEFAULT_OUTPUTS, OUTPUT_LEVELS
from mpi_lidar.reporting.scan_outputs import write_scan_outputs
from mpi_lidar.scans.scan import Scan
from mpi_lidar.scans.store import read_scan, write_scan
from mpi_lidar.simulation.dataset import seeded_rng, simulate_rows
from mpi_lidar.simulation.sampling import THETA_NAMES
from mpi_lidar.simulation.scenes import SCENES, render
from mpi_lidar.workflows.correct_archive import correct_archive, process_scan

STAGE_HEADERS = ("stage", "CPU s", "CPU s per megapixel", "share of the light run")
END_TO_END_HEADERS = ("run", "pixels", "wall s", "CPU s", "pixels/s", "target", "met")
INFERENCE_HEADERS = ("run", "pixels", "wall s", "CPU s", "end to end / pure inference", "target", "met")
BATCH_HEADERS = ("batch", "scans", "wall s", "s per scan", "pixel cost per scan s", "overhead per scan s", "target",
                 "met")
MEMORY_HEADERS = ("scan", "pixels", "peak RSS MiB", "after imports and model MiB", "growth MiB",
                  "growth bytes per pixel", "target", "met")
SCENE = "cornered_board"
PATCH_SPACING_M = 0.05  # coarse patches keep a megapixel render short; correction cost does not depend on them
TARGET_PIXELS_PER_S = 1_000_000
TARGET_INFERENCE_RATIO = 3.0
TARGET_OVERHEAD_S = 0.2
TARGET_PEAK_BYTES = 2**30
TARGET_PEAK_SIDE = 4000
REPOSITORY = Path(__file__).resolve().parents[1]


@dataclass(frozen=True)
class Plan:
    """Sizes of one run."""

    side: int = 1000
    batch: int = 200
    batch_side: int = 256
    big_side: int = 4000
    train_rows: int = 50_000
    rounds: int = DEFAULT_ROUNDS
    repeats: int = 3  # end-to-end runs per output level and pure-inference runs; the fastest is reported
    startup_repeats: int = 5  # fresh processes per start-up row; the median is reported

    @classmethod
    def quick(cls) -> Plan:
        return cls(side=48, batch=3, batch_side=24, big_side=96, train_rows=2_000, rounds=10, repeats=1,
                   startup_repeats=1)


def table(headers: tuple[str, ...], rows: list[tuple[object, ...]]) -> str:
    lines = ["| " + " | ".join(headers) + " |", "|" + "---|" * len(headers)]
    lines += ["| " + " | ".join(str(cell) for cell in row) + " |" for row in rows]
    return "\n".join(lines)


def _met(ok: bool | None) -> str:
    return "" if ok is None else "yes" if ok else "no"


# --- inputs -----------------------------------------------------------------------------------------------


def trained_model(out: Path, rows: int, rounds: int) -> Path:
    """A model of the default feature set, target and geometric inputs, trained in this process."""
    if out.exists():
        return out
    config = Config()
    spec = FeatureSpec(config.frequencies_hz, DEFAULT_FEATURE_SET, DEFAULT_TARGET_MODE, geometric=True)
    raw, theta = simulate_rows(config, rows, seeded_rng(config.dataset.seed, 0))
    geometry = synthetic_geometry(theta, THETA_NAMES, config.dataset.seed, np.arange(rows))
    early = DEFAULT_EARLY_STOPPING if rounds > DEFAULT_EARLY_STOPPING else None
    fitted = train_arrays(spec.transform(raw, geometry), spec.target(raw, theta[:, 0]), None, rounds, early,
                          nthread=os.cpu_count() or 1)
    card = model_card(spec, DatasetCard.from_config(config, path="simulated in benchmarks.correction"), None,
                      fitted, workers=0)
    return save_model(out, fitted.booster, card)


def rendered(work: Path, side: int) -> Path:
    """The cornered board rendered at side x side, stored in ``work`` (reused when there)."""
    path = work / f"{SCENE}-{side}.scan.zarr"
    if not path.exists():
        scan = render(SCENES[SCENE](height=side, width=side), Config(), np.random.default_rng(0),
                      patch_spacing_m=PATCH_SPACING_M)
        write_scan(scan, path)
    return path


def upsampled(source: Path, out: Path, factor: int) -> Path:
    """The store of ``source`` upsampled (:func:`finer_scan`) into ``out`` (reused when there)."""
    if not out.exists():
        write_scan(finer_scan(read_scan(source), factor), out)
    return out


def finer_scan(scan: Scan, factor: int) -> Scan:
    """The scan with every pixel repeated factor x factor times on a grid factor times finer."""

    def grow(values: np.ndarray | None) -> np.ndarray | None:
        return None if values is None else np.repeat(np.repeat(values, factor, axis=-2), factor, axis=-1)

    def finer(angles: np.ndarray) -> np.ndarray:
        step = (angles[-1] - angles[0]) / max(len(angles) - 1, 1)
        return np.linspace(angles[0] - step / 2 + step / (2 * factor), angles[-1] + step / 2 - step / (2 * factor),
                           len(angles) * factor)

    return replace(scan, name=f"{scan.name}-x{factor}", depth=grow(scan.depth), amplitude=grow(scan.amplitude),
                   azimuth_rad=finer(scan.azimuth_rad), elevation_rad=finer(scan.elevation_rad),
                   reference_depth=grow(scan.reference_depth), reference_mask=grow(scan.reference_mask))


def batch_archive(work: Path, source: Path, scans: int) -> Path:
    """``scans`` copies of one scan under their own names, in one directory."""
    archive = work / f"batch-{scans}-{source.name.removesuffix('.scan.zarr')}"
    archive.mkdir(exist_ok=True)
    scan = read_scan(source)
    for index in range(scans):
        path = archive / f"s{index:04d}.scan.zarr"
        if not path.exists():
            write_scan(replace(scan, name=f"s{index:04d}"), path)
    return archive


# --- measurements -----------------------------------------------------------------------------------------


def _cpu_wall(fn, *args, **kwargs):
    cpu, wall = time.process_time(), time.perf_counter()
    result = fn(*args, **kwargs)
    return result, time.process_time() - cpu, time.perf_counter() - wall


def stages(source: Path, model_dir: Path, work: Path) -> tuple[list[tuple[object, ...]], dict[str, float]]:
    """Rows of table 1 and the CPU seconds per stage of the light run."""
    model = load_model(model_dir)
    options = CorrectionOptions()
    read_scan(source)  # warm the file cache
    scan, read_cpu, _ = _cpu_wall(read_scan, source)
    correct_scan(scan, model, options)  # warm: noise model, first-call costs
    correction = correct_scan(scan, model, options)
    needs = np.flatnonzero(np.isin(correction.flags.ravel(), MODEL_FLAGS))
    raw = scan.raw_pixels()[needs]
    geometry = np.zeros((needs.size, 2)) if model.geometric else None  # computed by the gate; here only copied
    _, features_cpu, _ = _cpu_wall(model.spec.transform, raw, geometry)
    # The stages of correct_scan (Correction.cpu_s): the amplitude unit, validity (the first pass), the gate (the
    # scene geometry and the geometric inputs), inference, and the baseline (fusion and uncertainty, in the second).
    cpu = {"read": read_cpu, "unit": correction.cpu_s.get("unit", 0.0),
           "validity": correction.cpu_s.get("validity", 0.0), "gate": correction.cpu_s.get("gate", 0.0),
           "features": min(features_cpu, correction.cpu_s.get("inference", 0.0)),
           "inference": max(correction.cpu_s.get("inference", 0.0) - features_cpu, 0.0),
           "baseline": correction.cpu_s.get("baseline", 0.0)}
    metrics = scan_metrics(scan, correction)
    written: dict[str, dict[str, float]] = {}
    for level in OUTPUT_LEVELS:
        seconds: dict[str, float] = {}
        target = work / "stage-outputs" / level
        shutil.rmtree(target, ignore_errors=True)
        target.parent.mkdir(parents=True, exist_ok=True)
        write_scan_outputs(target, scan, correction, metrics, {}, options, level, seconds)
        written[level] = seconds
    megapixels = scan.shape[0] * scan.shape[1] / 1e6
    light = {**cpu, "write": written["light"].get("write", 0.0), "figures": written["light"].get("figures", 0.0)}
    total = sum(light.values())
    rows: list[tuple[object, ...]] = []
    for name, seconds in cpu.items():
        rows.append((name, f"{seconds:.2f}", f"{seconds / megapixels:.3f}", f"{100 * seconds / total:.0f} %"))
    for level in ("data", "light", "full"):
        for part in ("write", "figures"):
            seconds = written[level].get(part, 0.0)
            share = f"{100 * seconds / total:.0f} %" if level == "light" else ""
            rows.append((f"{part} ({level})", f"{seconds:.2f}", f"{seconds / megapixels:.3f}", share))
    rows.append(("total, light outputs", f"{total:.2f}", f"{total / megapixels:.3f}", "100 %"))
    return rows, light


def end_to_end(source: Path, model_dir: Path, work: Path, pixels: int, repeats: int
               ) -> tuple[list[tuple[object, ...]], float]:
    """Rows of table 2 (the fastest of ``repeats`` runs per level) and the wall seconds of the default run."""
    rows: list[tuple[object, ...]] = []
    options = CorrectionOptions()
    process_scan(source, model_dir, work / "e2e-warm", options, outputs="data")  # the model is cached from here
    default_wall = float("nan")
    for level in reversed(OUTPUT_LEVELS):
        runs = []
        for _ in range(repeats):
            out = work / f"e2e-{level}"
            shutil.rmtree(out, ignore_errors=True)
            outcome, cpu, wall = _cpu_wall(process_scan, source, model_dir, out, options, outputs=level)
            if outcome.status == "failed":
                raise SystemExit(f"correction failed: {outcome.reason}")
            runs.append((wall, cpu))
        wall, cpu = min(runs)
        default = level == DEFAULT_OUTPUTS
        default_wall = wall if default else default_wall
        rows.append((f"process_scan, outputs {level}" + (" (default)" if default else ""), f"{pixels:,}",
                     f"{wall:.2f}", f"{cpu:.2f}", f"{pixels / wall:,.0f}",
                     f">= {TARGET_PIXELS_PER_S:,}" if default else "",
                     _met(pixels / wall >= TARGET_PIXELS_PER_S) if default else ""))
    out = work / "e2e-cli"
    shutil.rmtree(out, ignore_errors=True)
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    started = time.perf_counter()
    done = subprocess.run([sys.executable, "-m", "mpi_lidar.cli", "correct", str(source), "--model", str(model_dir),
                           "--out", str(out)], capture_output=True, text=True)
    wall = time.perf_counter() - started
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    child_cpu = after.ru_utime + after.ru_stime - before.ru_utime - before.ru_stime
    if done.returncode not in (0, 1):
        raise SystemExit(f"mpi-lidar correct failed: {done.stderr.strip()}")
    rows.append(("mpi-lidar correct, one scan, defaults (imports and model included)", f"{pixels:,}", f"{wall:.2f}",
                 f"{child_cpu:.2f}", f"{pixels / wall:,.0f}", "", ""))
    return rows, default_wall


def pure_inference(source: Path, model_dir: Path, end_to_end_s: float, repeats: int) -> list[tuple[object, ...]]:
    """Row of table 3: inplace_predict of the model on the features of every pixel of the scan (fastest run)."""
    model = load_model(model_dir)
    scan = read_scan(source)
    raw = scan.raw_pixels()
    geometry = np.zeros((raw.shape[0], 2)) if model.geometric else None
    features = model.spec.transform(raw, geometry)
    model.booster.inplace_predict(features[:1000])  # warm
    runs = [_cpu_wall(model.booster.inplace_predict, features) for _ in range(repeats)]
    _, cpu, wall = min(runs, key=lambda run: run[2])
    ratio = end_to_end_s / wall
    return [(f"inplace_predict, every pixel ({model.booster.num_boosted_rounds()} trees)", f"{raw.shape[0]:,}",
             f"{wall:.2f}", f"{cpu:.2f}", f"{ratio:.1f}", f"<= {TARGET_INFERENCE_RATIO:g}",
             _met(ratio <= TARGET_INFERENCE_RATIO))]


def batch(archive: Path, model_dir: Path, work: Path, scans: int, pixels_per_scan: int,
          pixels_per_s: float) -> list[tuple[object, ...]]:
    """Rows of table 4: a batch in this process with the default outputs, the footprint measured per scan
    (``auto``, the default) and given (as a sensor profile gives it)."""
    rows = []
    for footprint, label in (("auto", "footprint auto"), (DEFAULT_FOOTPRINT_AREA_M2, "footprint given")):
        out = work / "batch-out"
        shutil.rmtree(out, ignore_errors=True)
        outcomes, _, wall = _cpu_wall(correct_archive, [str(archive)], model_dir, out,
                                      CorrectionOptions(footprint_area_m2=footprint), outputs=DEFAULT_OUTPUTS)
        failed = [o for o in outcomes if o.status == "failed"]
        if failed:
            raise SystemExit(f"batch: {failed[0].source}: {failed[0].reason}")
        per_scan = wall / scans
        pixel_cost = pixels_per_scan / pixels_per_s
        overhead = per_scan - pixel_cost
        side = math.isqrt(pixels_per_scan)
        rows.append((f"{side} x {side}, outputs {DEFAULT_OUTPUTS}, {label}, this process", scans, f"{wall:.1f}",
                     f"{per_scan:.3f}", f"{pixel_cost:.3f}", f"{overhead:.3f}", f"<= {TARGET_OVERHEAD_S:g}",
                     _met(overhead <= TARGET_OVERHEAD_S)))
    return rows


def peak_memory(source: Path, model_dir: Path, work: Path, side: int) -> tuple[object, ...]:
    """Row of table 5: a fresh process corrects the scan; its peak resident set and the growth over it."""
    out = work / f"peak-{side}"
    shutil.rmtree(out, ignore_errors=True)
    done = subprocess.run([sys.executable, "-m", "benchmarks.correction", "--peak-child", str(source),
                           str(model_dir), str(out)], capture_output=True, text=True, cwd=REPOSITORY)
    if done.returncode:
        raise SystemExit(f"peak-memory child failed: {done.stderr.strip()[-2000:]}")
    result = json.loads(done.stdout.strip().splitlines()[-1])
    pixels = side * side
    growth = result["peak_bytes"] - result["before_bytes"]
    checked = side >= TARGET_PEAK_SIDE
    return (f"{side} x {side}", f"{pixels:,}", f"{result['peak_bytes'] / 2**20:,.0f}",
            f"{result['before_bytes'] / 2**20:,.0f}", f"{growth / 2**20:,.0f}", f"{growth / pixels:.0f}",
            "<= 1 GiB peak" if checked else "", _met(result["peak_bytes"] <= TARGET_PEAK_BYTES) if checked else "")


def peak_rss_bytes() -> int:
    """This process's peak resident set [bytes]: VmHWM where Linux gives it (ru_maxrss after fork and exec
    also counts the parent's resident set at the fork), else ru_maxrss."""
    try:
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith("VmHWM:"):
                return int(line.split()[1]) * 1024
    except OSError:
        pass
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024


def _peak_child(source: str, model_dir: str, out: str) -> None:
    from mpi_lidar.workflows.correct_archive import _cached_model

    _cached_model(model_dir)
    before = peak_rss_bytes()
    outcome = process_scan(source, model_dir, out, CorrectionOptions(), outputs=DEFAULT_OUTPUTS)
    peak = peak_rss_bytes()
    print(json.dumps({"status": str(outcome.status), "reason": outcome.reason, "before_bytes": before,
                      "peak_bytes": peak}))


def machine() -> str:
    load = ", ".join(f"{x:.1f}" for x in os.getloadavg())
    return (f"Machine: {platform.node()} ({platform.machine()}), {os.cpu_count()} cores, Python "
            f"{platform.python_version()}, {date.today()}; load average {load} at the start")


def memory_table(plan: Plan, model_dir: Path, work: Path, source: Path) -> str:
    """Table 5: the peak memory of the ``--side`` scan and of the ``--big-side`` one."""
    big = upsampled(source, work / f"{SCENE}-{plan.big_side}.scan.zarr", max(1, plan.big_side // plan.side))
    big_side = read_scan(big).shape[0] if plan.big_side != plan.side else plan.side
    return table(MEMORY_HEADERS, [peak_memory(source, model_dir, work, plan.side),
                                  peak_memory(big, model_dir, work, big_side)])


def run_only(table_name: str, plan: Plan, model_dir: Path | None, work: Path) -> str:
    """One table alone (``memory``: table 5, ``startup``: table 6), printed when measured."""
    work.mkdir(parents=True, exist_ok=True)
    parts = [machine()]
    if table_name == "startup":
        parts.append(startup_tables(work / "startup", plan.startup_repeats))
    else:
        model_dir = model_dir or trained_model(work / f"model-{plan.train_rows}-{plan.rounds}", plan.train_rows,
                                               plan.rounds)
        parts.append(memory_table(plan, model_dir, work, rendered(work, plan.side)))
    text = "\n\n".join(parts)
    print(text, flush=True)
    return text


def run(plan: Plan, model_dir: Path | None, work: Path) -> str:
    """Every table of one run, as markdown, each printed as soon as it is measured."""
    work.mkdir(parents=True, exist_ok=True)
    parts = [machine()]
    print(parts[0], flush=True)
    model_dir = model_dir or trained_model(work / f"model-{plan.train_rows}-{plan.rounds}", plan.train_rows,
                                           plan.rounds)
    source = rendered(work, plan.side)
    pixels = plan.side * plan.side
    trees = load_model(model_dir).booster.num_boosted_rounds()
    sections = [f"Model {model_dir} ({trees} trees); scene {SCENE} {plan.side} x {plan.side} ({source})."]

    def emit(text: str) -> None:
        sections.append(text)
        print("\n" + text, flush=True)

    print(sections[0], flush=True)
    stage_rows, _ = stages(source, model_dir, work)
    emit(table(STAGE_HEADERS, stage_rows))
    e2e_rows, default_wall = end_to_end(source, model_dir, work, pixels, plan.repeats)
    emit(table(END_TO_END_HEADERS, e2e_rows))
    emit(table(INFERENCE_HEADERS, pure_inference(source, model_dir, default_wall, plan.repeats)))
    archive = batch_archive(work, rendered(work, plan.batch_side), plan.batch)
    emit(table(BATCH_HEADERS, batch(archive, model_dir, work, plan.batch, plan.batch_side**2, pixels / default_wall)))
    emit(memory_table(plan, model_dir, work, source))
    emit(startup_tables(work / "startup", plan.startup_repeats))
    return "\n\n".join(parts + sections)


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--model", type=Path, help="Model directory (default: train one here).")
    parser.add_argument("--work", type=Path, help="Directory for renders, the model and outputs (kept).")
    parser.add_argument("--side", type=int, help="Side of the end-to-end scan [px] (default 1000).")
    parser.add_argument("--batch", type=int, help="Scans of the batch (default 200).")
    parser.add_argument("--batch-side", type=int, help="Side of the batch's scans [px] (default 256).")
    parser.add_argument("--big-side", type=int, help="Side of the big peak-memory scan [px] (default 4000).")
    parser.add_argument("--train-rows", type=int, help="Rows the model is trained on (default 50,000).")
    parser.add_argument("--quick", action="store_true", help="Tiny sizes (seconds): for a first look and tests.")
    parser.add_argument("--only", choices=("memory", "startup"),
                        help="One table alone: the peak memory (5) or the start-up (6).")
    parser.add_argument("--peak-child", nargs=3, metavar=("SCAN", "MODEL", "OUT"), help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.peak_child:
        _peak_child(*args.peak_child)
        return
    plan = Plan.quick() if args.quick else Plan()
    sizes = {"side": args.side, "batch": args.batch, "batch_side": args.batch_side, "big_side": args.big_side,
             "train_rows": args.train_rows}
    plan = dataclasses.replace(plan, **{k: v for k, v in sizes.items() if v is not None})
    work = args.work or Path(tempfile.gettempdir()) / "mpi-lidar-bench-correction"
    if args.only:
        run_only(args.only, plan, args.model, work)
    else:
        run(plan, args.model, work)


if __name__ == "__main__":
    main()
