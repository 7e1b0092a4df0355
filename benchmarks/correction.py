"""Correction throughput on a 1-megapixel scan, with every valid pixel corrected and with skipping.

Run: .venv/bin/python -m benchmarks.correction --model runs/quick/model [--pixels 1000000] [--scene NAME]
The scan is a rendered scene (default: the cornered board) at about ``--pixels`` pixels. Prints pixels per
second of `correct_scan` (validity mask, gate, inference in tiles) in this process, the share of pixels
skipped by the gate, the MAE on the reference mask and the gate's own speed for each gate.
"""

from __future__ import annotations

import argparse
import platform
import time
from datetime import date

import numpy as np

from mpi_lidar.config import Config
from mpi_lidar.correct import CorrectionOptions, Flag, correct_scan
from mpi_lidar.model import load_model
from mpi_lidar.scenes import SCENES, render


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--model", required=True)
    parser.add_argument("--pixels", type=int, default=1_000_000)
    parser.add_argument("--scene", default="cornered_board", choices=sorted(SCENES))
    args = parser.parse_args()
    side = round(np.sqrt(args.pixels))
    started = time.perf_counter()
    # Coarse patches keep a megapixel render short; correction cost does not depend on them.
    scan = render(SCENES[args.scene](height=side, width=side), Config(), np.random.default_rng(0),
                  patch_spacing_m=0.05)
    render_s = time.perf_counter() - started
    model = load_model(args.model)
    print(f"Machine: {platform.node()} ({platform.machine()}), {date.today()}; scene {args.scene} "
          f"{side} x {side} rendered in {render_s:.1f} s; model {args.model} "
          f"({model.booster.num_boosted_rounds()} trees)\n")
    print("| gate | pixels/s | corrected | skipped by the gate | out of range | invalid | masked raw MAE [mm] | "
          "masked corrected MAE [mm] | gate alone, pixels/s |")
    print("|---|---|---|---|---|---|---|---|---|")
    mask = scan.reference_mask
    for gate in ("all", "consistency", "geometry"):
        correct_scan(scan, model, CorrectionOptions(gate=gate))  # warm caches
        correction = correct_scan(scan, model, CorrectionOptions(gate=gate))
        flags = correction.flags
        share = {f: (flags == f).mean() for f in Flag}
        usable = mask & np.isfinite(correction.depth)
        raw = np.abs(scan.depth[-1][usable] - scan.reference_depth[usable]).mean()
        corrected = np.abs(correction.depth[usable] - scan.reference_depth[usable]).mean()
        skipped = share[Flag.NOT_NEEDED] + share[Flag.NO_MULTIPATH]
        invalid = 1 - share[Flag.CORRECTED] - skipped - share[Flag.OUT_OF_RANGE]
        print(f"| {gate} | {flags.size / correction.total_s:,.0f} | {100 * share[Flag.CORRECTED]:.1f} % | "
              f"{100 * skipped:.1f} % | {100 * share[Flag.OUT_OF_RANGE]:.1f} % | {100 * invalid:.1f} % | "
              f"{1e3 * raw:.3f} | {1e3 * corrected:.3f} | {flags.size / max(correction.gate_s, 1e-9):,.0f} |")

if __name__ == "__main__":
    main()
