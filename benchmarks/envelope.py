"""The correction's envelope: corners and walls at any range, wrapped depths, amplitudes in another unit.

Run: .venv/bin/python -m benchmarks.envelope --model DIR [--seed 0] [--quick]
Renders a 90-degree corner of albedo 0.7 boards that fill the view (receiver footprint 0.073 m^2, Table I noise)
with its edge at 1, 2, 3.5 and 6 m (past 4.8 m the 31.25 and 25 MHz depths wrap), a weak corner (0.002 m^2) and
a flat wall at the same ranges, and the 2 m corner with its amplitudes in counts (x 4000) and x 0.01, given with
their unit (``amplitude_scale``) and without. Each is corrected with default options (footprint ``auto``) and prints one
markdown row: the scan's status (and why, where unserved), the MAE of the measured 31.25 MHz depth (unwrapped)
and of the corrected depth on the pixels both have, the same within 20 cm of the corner's edge, and the edge's
error change. ``--quick`` runs the corners at 1 and 6 m only, small (for a test).
"""

from __future__ import annotations

import argparse
import platform
import time
from dataclasses import dataclass, replace
from datetime import date

import numpy as np

from benchmarks.scenes import edge_line, edge_line_region, mae_mm
from mpi_lidar.config import Config
from mpi_lidar.correction import INVALID_FLAGS, CorrectionOptions, correct_scan
from mpi_lidar.correction.outcome import scan_status
from mpi_lidar.learning.model import CorrectionModel, load_model
from mpi_lidar.physics.coupling import DEFAULT_FOOTPRINT_RADIUS_M
from mpi_lidar.scans.scan import Scan
from mpi_lidar.simulation.scenes import Scene, corner, flat_wall, render

STRONG_M2, WEAK_M2 = 0.073, 0.002
RANGES_M = (1.0, 2.0, 3.5, 6.0)
HEADER = ("| scan | status | raw MAE [mm] | corrected MAE [mm] | edge raw [mm] | edge corrected [mm] | edge change "
          "| note |\n|---|---|---|---|---|---|---|---|")


@dataclass(frozen=True)
class Case:
    """One scan of the run: its label, scene, its corner's edge distance [m] (None: no corner), true footprint
    [m^2], amplitude unit per V^2, and the unit the correction is told (None: V^2, the default)."""

    label: str
    scene: Scene
    edge_m: float | None
    footprint_m2: float
    unit: float = 1.0
    told_unit: float | None = None


def framed_corner(distance_m: float, albedo: float = 0.7, height: int = 96, width: int = 128) -> Scene:
    """A 90-degree corner at ``distance_m`` whose boards fill the view at any range."""
    return corner(90.0, distance_m, albedo, height, width, board_m=max(0.5, 0.25 * distance_m),
                  half_height_m=max(0.35, 0.12 * distance_m))


def render_with_footprint(scene: Scene, footprint_m2: float, seed: int) -> Scan:
    """The scene rendered at Table I noise with the receiver footprint ``footprint_m2`` [m^2] (0: a wall, coarse
    patches: no multipath to render)."""
    gain = footprint_m2 / (np.pi * DEFAULT_FOOTPRINT_RADIUS_M**2)
    return render(scene, Config(), np.random.default_rng(seed), coupling_gain=gain,
                  patch_spacing_m=1.0 if footprint_m2 == 0 else None)


def cases(quick: bool) -> list[Case]:
    size = {"height": 48, "width": 64} if quick else {}
    ranges = (1.0, 6.0) if quick else RANGES_M
    runs = [Case(f"corner 90 deg at {d:g} m, strong", framed_corner(d, **size), d, STRONG_M2) for d in ranges]
    if quick:
        return runs
    runs += [Case(f"corner 90 deg at {d:g} m, weak", framed_corner(d), d, WEAK_M2) for d in RANGES_M]
    runs += [Case(f"wall at {d:g} m", flat_wall(20.0, d, 0.7), None, 0.0) for d in RANGES_M]
    two = framed_corner(2.0)
    runs += [Case("corner at 2 m in counts (x 4000), unit given", two, 2.0, STRONG_M2, 4000.0, 4000.0),
             Case("corner at 2 m in counts (x 4000), unit not given", two, 2.0, STRONG_M2, 4000.0),
             Case("corner at 2 m x 0.01, unit given", two, 2.0, STRONG_M2, 0.01, 0.01)]
    return runs


def rendered(case: Case, seed: int) -> Scan:
    scan = render_with_footprint(case.scene, case.footprint_m2, seed)
    return replace(scan, amplitude=(scan.amplitude * case.unit).astype(np.float32))


def row(case: Case, scan: Scan, model: CorrectionModel) -> str:
    options = CorrectionOptions() if case.told_unit is None else CorrectionOptions(amplitude_scale=case.told_unit)
    correction = correct_scan(scan, model, options)
    status = scan_status(correction.counts(), options.max_invalid_share,
                         None if correction.unserved is None else correction.unserved.reason)
    assert correction.measured_depth is not None and scan.reference_depth is not None
    usable = (np.isfinite(scan.reference_depth) & np.isfinite(correction.depth)
              & ~np.isin(correction.flags, [int(f) for f in INVALID_FLAGS]))
    edge = usable & (edge_line_region(scan, edge_line(case.edge_m)) if case.edge_m is not None else False)
    raw, fixed = (mae_mm(depth, scan.reference_depth, usable) for depth in (correction.measured_depth,
                                                                             correction.depth))
    edge_raw, edge_fixed = (mae_mm(depth, scan.reference_depth, edge) for depth in (correction.measured_depth,
                                                                                     correction.depth))
    change = f"{100 * (edge_fixed / edge_raw - 1):+.0f} %" if edge.any() and edge_raw > 0 else ""
    note = (f"{correction.unserved.reason}" if correction.unserved is not None
            else f"{int(usable.sum()):,} pixels, {correction.model_pixels():,} corrected")
    return (f"| {case.label} | {status} | {raw:.3f} | {fixed:.3f} | {_cell(edge_raw)} | {_cell(edge_fixed)} "
            f"| {change} | {note} |")


def _cell(value: float) -> str:
    return "" if not np.isfinite(value) else f"{value:.3f}"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--model", required=True)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--quick", action="store_true")
    args = parser.parse_args()
    model = load_model(args.model)
    prior = model.card.dataset.prior
    started = time.perf_counter()
    print(f"model {args.model}: d_AS {prior.d_as_m[0]:g}-{prior.d_as_m[1]:g} m ({prior.d_as_distribution}), "
          f"{model.spec.feature_set} inputs{', geometric' if model.geometric else ''}; default options; "
          f"Table I noise, seed {args.seed}\n")
    print(HEADER)
    for case in cases(args.quick):
        print(row(case, rendered(case, args.seed), model), flush=True)
    print(f"\n{platform.system()}, {platform.machine()}, Python {platform.python_version()}, {date.today()}, "
          f"{time.perf_counter() - started:.0f} s wall")


if __name__ == "__main__":
    main()
