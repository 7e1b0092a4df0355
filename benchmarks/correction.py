"""Correction throughput on a 1-megapixel scan, with every valid pixel corrected and with skipping.

Run: .venv/bin/python -m benchmarks.correction --model runs/quick/model [--pixels 1000000] [--scene NAME]
     [--scan PATH]
The scan is a rendered scene (default: the cornered board) at about ``--pixels`` pixels; with ``--scan`` it
is read from that store, or rendered and saved there if the store does not exist yet. Prints pixels per
second of `correct_scan` (validity mask, gate, inference in tiles) in this process, its CPU seconds (all
threads; robust when other jobs share the machine), the share of pixels skipped by the gate, the MAE on the
reference mask, and the gate's own speed and CPU seconds for each gate.
"""

from __future__ import annotations

import argparse
import platform
import time
from datetime import date
from pathlib import Path

import numpy as np

from mpi_lidar.config import Config, SensorConfig
from mpi_lidar.correction import CorrectionOptions, Flag, correct_scan, make_gate, validity_flags
from mpi_lidar.learning.model import load_model
from mpi_lidar.scans.scan import Scan, read_scan, write_scan
from mpi_lidar.simulation.scenes import SCENES, render


def gate_cpu_seconds(scan: Scan, gate: str) -> float:
    """CPU seconds of the gate alone on the scan's valid pixels (the validity mask excluded)."""
    options = CorrectionOptions(gate=gate)
    raw = scan.raw_pixels()
    f = len(scan.frequencies_hz)
    valid = np.flatnonzero(validity_flags(raw, scan.frequencies_hz, options, SensorConfig()) == Flag.NOT_NEEDED)
    depth = np.full(raw.shape[0], np.nan)
    depth[valid] = raw[valid, f - 1]
    started = time.process_time()
    gate_ = make_gate(options)
    gate_.scan_candidates(scan, depth)
    gate_.needs_correction(raw[valid], scan.frequencies_hz, SensorConfig())
    return time.process_time() - started


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--model", required=True)
    parser.add_argument("--pixels", type=int, default=1_000_000)
    parser.add_argument("--scene", default="cornered_board", choices=sorted(SCENES))
    parser.add_argument("--scan", type=Path, help="Scan store to reuse (rendered and saved there if missing).")
    args = parser.parse_args()
    side = round(np.sqrt(args.pixels))
    started = time.perf_counter()
    if args.scan is not None and args.scan.exists():
        scan = read_scan(args.scan)
        side = scan.shape[0]
    else:
        # Coarse patches keep a megapixel render short; correction cost does not depend on them.
        scan = render(SCENES[args.scene](height=side, width=side), Config(), np.random.default_rng(0),
                      patch_spacing_m=0.05)
        if args.scan is not None:
            write_scan(scan, args.scan)
    render_s = time.perf_counter() - started
    model = load_model(args.model)
    print(f"Machine: {platform.node()} ({platform.machine()}), {date.today()}; scene {args.scene} "
          f"{side} x {side} rendered or read in {render_s:.1f} s; model {args.model} "
          f"({model.booster.num_boosted_rounds()} trees)\n")
    print("| gate | pixels/s | corrected | skipped by the gate | out of range | invalid | masked raw MAE [mm] | "
          "masked corrected MAE [mm] | gate alone, pixels/s | CPU s | gate CPU s |")
    print("|---|---|---|---|---|---|---|---|---|---|---|")
    mask = scan.reference_mask
    for gate in ("all", "consistency", "geometry"):
        correct_scan(scan, model, CorrectionOptions(gate=gate))  # warm caches
        cpu = time.process_time()
        correction = correct_scan(scan, model, CorrectionOptions(gate=gate))
        cpu = time.process_time() - cpu
        gate_cpu = gate_cpu_seconds(scan, gate)
        flags = correction.flags
        share = {f: (flags == f).mean() for f in Flag}
        usable = mask & np.isfinite(correction.depth)
        raw = np.abs(scan.depth[-1][usable] - scan.reference_depth[usable]).mean()
        corrected = np.abs(correction.depth[usable] - scan.reference_depth[usable]).mean()
        skipped = share[Flag.NOT_NEEDED] + share[Flag.NO_MULTIPATH]
        invalid = 1 - share[Flag.CORRECTED] - skipped - share[Flag.OUT_OF_RANGE]
        print(f"| {gate} | {flags.size / correction.total_s:,.0f} | {100 * share[Flag.CORRECTED]:.1f} % | "
              f"{100 * skipped:.1f} % | {100 * share[Flag.OUT_OF_RANGE]:.1f} % | {100 * invalid:.1f} % | "
              f"{1e3 * raw:.3f} | {1e3 * corrected:.3f} | {flags.size / max(correction.gate_s, 1e-9):,.0f} | "
              f"{cpu:.2f} | {gate_cpu:.2f} |")

if __name__ == "__main__":
    main()
