"""Per-scan self-calibration of the receiver footprint A_fp: does "auto" correct as well as the true footprint?

Run: .venv/bin/python -m benchmarks.calibration --model DIR [--quick | --held-out | --several-surfaces] [--seed 0]
                                                [--scene TEXT]...
 or: .venv/bin/python -m benchmarks.calibration --model DIR --cost  (CPU the calibration adds to 1000 x 1000)
Renders every scene of the set with each true footprint A_fp (coupling gain A_fp / pi r^2, r the default
footprint radius), corrects it with the true A_fp and with ``footprint_area_m2="auto"`` (the scan measures its
own footprint), and prints one markdown row per scene and footprint: MAE of the 31.25 MHz depth on the usable
pixels before and after both corrections, the same within 20 cm of the corner edge (corners only), with the
edge's MAE once the render's own noise-free multipath is taken off the raw depth (what removing the multipath
exactly would leave: the noise), and the footprint the scan measured against the true one. A summary checks the
targets: "auto" never worse than raw by more than 0.05 mm, at the edge within 10 % of the true-A_fp correction
and at least 40 % better than raw where the raw edge error is above 3 mm (and on how many of those rows the exact
removal of the multipath would reach it), and the estimate within a factor 1.5 on corners whose edge multipath
(the mean signed raw error there) is above 2 mm. ``--quick`` runs two scenes at two footprints (for a test);
``--held-out`` runs, instead of the main set, five corners kept out of the method's development
(:data:`HELD_OUT`), and ``--several-surfaces`` scenes where more than two surfaces face each other or a floor is
seen obliquely (:data:`SEVERAL_SURFACES`); their "edge" is within 20 cm of any of their edges. ``--scene`` keeps
the scenes whose name contains the text, rendered as in the whole set (same seeds).
"""

from __future__ import annotations

import argparse
import math
import platform
import time
from collections.abc import Callable
from datetime import date
from typing import Any

import numpy as np

from benchmarks.scenes import EdgeLine, edge_line, edge_line_region, mae_mm
from mpi_lidar.config import Config
from mpi_lidar.correction import INVALID_FLAGS, CorrectionOptions, correct_scan
from mpi_lidar.learning.model import CorrectionModel, load_model
from mpi_lidar.physics.coupling import DEFAULT_FOOTPRINT_AREA_M2
from mpi_lidar.scans.scan import Scan
from mpi_lidar.simulation.scenes import (
    DEFAULT_FOOTPRINT_RADIUS_M,
    Scene,
    alcove,
    box_on_floor,
    corner,
    cylinder_scene,
    flat_wall,
    floor_meets_wall,
    multi_object,
    pitch_rotation,
    render,
    room_corner,
)

Case = tuple[str, Callable[[], Scene], tuple[EdgeLine, ...]]  # label, factory, the edges of its corners

# (angle [deg], edge distance [m], albedo): a spread over the three axes rather than their full product.
CORNERS = ((60, 1.4, 0.5), (60, 2.4, 0.9), (90, 1.4, 0.9), (90, 2.0, 0.1), (90, 2.4, 0.5), (120, 1.4, 0.9),
           (120, 2.0, 0.5))
FOOTPRINTS_M2 = (0.001, 0.004, 0.016, 0.041, 0.1)
QUICK_FOOTPRINTS_M2 = (0.002, 0.041)
ShapedCorner = tuple[str, float, float, float, dict[str, float]]  # label, angle [deg], edge distance [m], albedo,
#                                                                  the corner's keyword arguments
# Corners first held out, then part of the development: the first five showed the faults in the planes of
# the flat partners (their blocks' normals, the pixels read past an edge), the next five the bend of the boards
# at strong multipath. Other angles, distances and albedos; boards far beyond the view, ending inside it along
# and across the edge or at its border; views off the bisector; horizontal and rolled edges; two albedos.
SHAPED_CORNERS: tuple[ShapedCorner, ...] = (
    ("corner 75 deg, 1.8 m, albedo 0.3, boards 1 m, yaw 10 deg", 75, 1.8, 0.3, {"board_m": 1.0, "yaw_deg": 10}),
    ("corner 105 deg, 2.2 m, albedo 0.7, boards 0.25 m, yaw -15 deg", 105, 2.2, 0.7,
     {"board_m": 0.25, "yaw_deg": -15}),
    ("corner 90 deg, 2 m, albedo 0.6, horizontal edge", 90, 2.0, 0.6,
     {"board_m": 0.6, "half_height_m": 0.5, "roll_deg": 90}),
    ("corner 80 deg, 2.3 m, albedo 0.8 / 0.3, boards 0.2 m high", 80, 2.3, 0.8,
     {"half_height_m": 0.2, "albedo_right": 0.3}),
    ("corner 90 deg, 1.6 m, albedo 0.5, boards 0.8 m, yaw 25 deg", 90, 1.6, 0.5, {"board_m": 0.8, "yaw_deg": 25}),
    ("corner 70 deg, 2.1 m, albedo 0.4, boards 0.7 m, yaw -20 deg", 70, 2.1, 0.4, {"board_m": 0.7, "yaw_deg": -20}),
    ("corner 100 deg, 1.5 m, albedo 0.85, boards 0.35 m, edge rolled 30 deg", 100, 1.5, 0.85,
     {"board_m": 0.35, "roll_deg": 30}),
    ("corner 85 deg, 2 m, albedo 0.25 / 0.9, boards 0.15 m high", 85, 2.0, 0.25,
     {"half_height_m": 0.15, "albedo_right": 0.9}),
    ("corner 110 deg, 1.9 m, albedo 0.6, horizontal edge, yaw 10 deg", 110, 1.9, 0.6,
     {"board_m": 0.6, "half_height_m": 0.5, "roll_deg": 90, "yaw_deg": 10}),
    ("corner 65 deg, 1.7 m, albedo 0.7, boards 0.4 m, edge rolled -45 deg", 65, 1.7, 0.7,
     {"board_m": 0.4, "roll_deg": -45}),
)
# Corners held out of the method's development (``--held-out``), fixed before any of them was run: an edge
# rolled 60 degrees and seen 15 degrees off the bisector, a dark 55-degree corner, a 125-degree corner of
# boards 0.3 m high and two albedos, short bright boards near the far end of the prior's range, and a
# horizontal edge at 1.45 m.
HELD_OUT: tuple[ShapedCorner, ...] = (
    ("corner 95 deg, 1.7 m, albedo 0.55, yaw 15 deg, edge rolled 60 deg", 95, 1.7, 0.55,
     {"yaw_deg": 15, "roll_deg": 60}),
    ("corner 55 deg, 2 m, albedo 0.35, boards 0.6 m", 55, 2.0, 0.35, {"board_m": 0.6}),
    ("corner 125 deg, 1.6 m, albedo 0.8 / 0.5, boards 0.3 m high", 125, 1.6, 0.8,
     {"half_height_m": 0.3, "albedo_right": 0.5}),
    ("corner 85 deg, 2.35 m, albedo 0.95, boards 0.3 m, yaw -10 deg", 85, 2.35, 0.95,
     {"board_m": 0.3, "yaw_deg": -10}),
    ("corner 100 deg, 1.45 m, albedo 0.65, horizontal edge, boards 0.45 m", 100, 1.45, 0.65,
     {"board_m": 0.45, "half_height_m": 0.5, "roll_deg": 90}),
)


def _pitched_edge(point: tuple[float, float, float], direction: tuple[float, float, float], pitch_deg: float
                  ) -> EdgeLine:
    turn = pitch_rotation(pitch_deg)
    return turn @ np.asarray(point, dtype=np.float64), turn @ np.asarray(direction, dtype=np.float64)


_X, _Y, _Z = (1.0, 0.0, 0.0), (0.0, 1.0, 0.0), (0.0, 0.0, 1.0)
# Scenes of several surfaces (``--several-surfaces``), fixed and first run with the method as it stood, none of
# them looked at during its development: three surfaces meeting in a room's corner, an alcove whose parallel
# sides face each other, a box on a floor seen from a tripod (its hidden sides light the floor too) and a floor
# meeting a wall seen from a tripod, the floor at 20-27 degrees from the view.
SEVERAL_SURFACES: tuple[Case, ...] = (
    ("room corner: two walls and the floor, albedo 0.7", room_corner,
     ((np.array([-0.3, 0.0, 2.2]), np.array(_Y)), (np.array([0.0, -0.2, 2.2]), np.array(_X)),
      (np.array([-0.3, -0.2, 0.0]), np.array(_Z)))),
    ("alcove 0.6 m wide and deep, albedo 0.5", alcove,
     ((np.array([-0.3, 0.0, 2.3]), np.array(_Y)), (np.array([0.3, 0.0, 2.3]), np.array(_Y)))),
    ("box on a floor, tripod 27 deg down, albedo 0.8 / floor 0.4", box_on_floor,
     (_pitched_edge((0.0, -1.0, 2.0), _X, 27.0),)),
    ("floor meets wall, tripod 20 deg down, albedo 0.6 / 0.7", floor_meets_wall,
     (_pitched_edge((0.0, -1.0, 2.6), _X, 20.0),)),
)

# Targets of the summary.
MAX_AUTO_HARM_MM = 0.05
MAX_EDGE_RATIO = 1.10
STRONG_EDGE_MM = 3.0
MIN_EDGE_REDUCTION = 0.40
ESTIMATE_EDGE_MM = 2.0
MAX_ESTIMATE_FACTOR = 1.5

HEADER = ("| scene | true A_fp [m^2] | raw MAE [mm] | corrected, true A_fp [mm] | corrected, auto [mm] | edge raw [mm] "
          "| edge true A_fp [mm] | edge auto [mm] | edge multipath [mm] | edge, multipath removed [mm] "
          "| estimated A_fp [m^2] (+-sigma) | estimate / true | significant |\n"
          + "|---" * 13 + "|")


def corner_case(angle: float, distance: float, albedo: float) -> Case:
    return (f"corner {angle:g} deg, {distance:g} m, albedo {albedo:g}",
            lambda: corner(float(angle), distance, albedo), (edge_line(distance),))


def shaped_cases(corners: tuple[ShapedCorner, ...]) -> list[Case]:
    return [(label, lambda a=angle, d=distance, r=albedo, k=shape: corner(float(a), d, r, **k),
             (edge_line(distance, shape.get("roll_deg", 0.0)),))
            for label, angle, distance, albedo, shape in corners]


def scene_cases(quick: bool, held_out: bool = False, several_surfaces: bool = False) -> list[Case]:
    """The scenes of the run: corners (with an edge region) and scenes without facing surfaces or with several;
    with ``held_out`` the corners kept out of the method's development instead, with ``several_surfaces``
    the scenes of :data:`SEVERAL_SURFACES`."""
    if quick:
        return [corner_case(90, 2.0, 0.5), ("flat wall 0 deg", lambda: flat_wall(0.0), ())]
    if held_out:
        return shaped_cases(HELD_OUT)
    if several_surfaces:
        return list(SEVERAL_SURFACES)
    cases = [corner_case(*spec) for spec in CORNERS] + shaped_cases(SHAPED_CORNERS)
    cases += [(f"flat wall {tilt} deg", lambda tilt=tilt: flat_wall(float(tilt)), ()) for tilt in (0, 45)]
    return [*cases, ("cylinder", cylinder_scene, ()), ("multi-object (Fig. 8)", multi_object, ())]


def chosen_cases(quick: bool, held_out: bool, several_surfaces: bool, scenes: tuple[str, ...]
                 ) -> list[tuple[int, Case]]:
    """The run's cases with their index in the whole set (their seed), only those whose label contains one of
    ``scenes`` where any are given; ValueError where none does."""
    cases = list(enumerate(scene_cases(quick, held_out, several_surfaces)))
    if not scenes:
        return cases
    chosen = [(index, case) for index, case in cases if any(text in case[0] for text in scenes)]
    if not chosen:
        raise ValueError(f"no scene of the set is named like {', '.join(map(repr, scenes))}: "
                         "run without --scene to see the names")
    return chosen


def near_edges(scan: Scan, edges: tuple[EdgeLine, ...]) -> np.ndarray:
    """Pixels whose true surface point lies within EDGE_RADIUS_M of any of ``edges``."""
    near = np.zeros(scan.shape, dtype=bool)
    for edge in edges:
        near |= edge_line_region(scan, edge)
    return near


def coupling_gain(footprint_m2: float) -> float:
    """The renderer's coupling gain that gives the footprint A_fp = gain pi r^2 at the default radius."""
    return footprint_m2 / (np.pi * DEFAULT_FOOTPRINT_RADIUS_M**2)


def usable_pixels(scan: Scan, *flag_maps: np.ndarray) -> np.ndarray:
    """Pixels valid in every correction and with a finite reference: all MAEs of a row share them."""
    invalid = [int(f) for f in INVALID_FLAGS]
    usable = np.isfinite(scan.reference_depth)
    for flags in flag_maps:
        usable &= ~np.isin(flags, invalid)
    return usable


def measure_row(label: str, scan: Scan, edges: tuple[EdgeLine, ...], model: CorrectionModel,
                true_m2: float, true_bias_m: np.ndarray) -> dict[str, Any]:
    """Raw, true-A_fp and auto MAEs of one rendered scan, and the footprint it measured.

    ``true_bias_m`` (H, W) is the render's noise-free multipath bias of the 31.25 MHz depth: the raw depth
    less it is what a perfect removal of the multipath would leave (the noise), the edge's floor for any
    correction of the multipath.
    """
    # The raw baseline: pixels the model leaves alone keep the measured depth, so the rows compare footprints only.
    known = correct_scan(scan, model, CorrectionOptions(footprint_area_m2=true_m2, baseline="raw"))
    auto = correct_scan(scan, model, CorrectionOptions(footprint_area_m2="auto", baseline="raw"))
    usable = usable_pixels(scan, known.flags, auto.flags)
    near = usable & near_edges(scan, edges)
    raw, reference = scan.depth[-1], scan.reference_depth
    estimate = auto.calibration
    row: dict[str, Any] = {"scene": label, "corner": bool(edges), "true_m2": true_m2}
    for name, depth in (("raw", raw), ("true", known.depth), ("auto", auto.depth)):
        row[f"{name}_mm"] = mae_mm(depth, reference, usable)
        row[f"edge_{name}_mm"] = mae_mm(depth, reference, near) if edges else float("nan")
    # The multipath near the edge: the mean signed raw error there (the noise averages out, the bias does not).
    row["edge_multipath_mm"] = float(1e3 * np.mean((raw - reference)[near])) if near.any() else float("nan")
    row["edge_removed_mm"] = mae_mm(raw - true_bias_m, reference, near) if edges else float("nan")
    row["estimate_m2"] = estimate.area_m2 if estimate is not None else float("nan")
    row["sigma_m2"] = estimate.sigma_m2 if estimate is not None else float("inf")
    row["significant"] = bool(estimate is not None and estimate.significant)
    row["pixels"] = estimate.pixels if estimate is not None else 0
    return row


def run(model_path: str, quick: bool = False, seed: int = 0, held_out: bool = False,
        on_row: Callable[[dict[str, Any]], None] | None = None, several_surfaces: bool = False,
        scenes: tuple[str, ...] = ()) -> list[dict[str, Any]]:
    """One row per scene and true footprint (see :func:`measure_row`); ``on_row`` sees each as it is done.

    ``scenes``: only the scenes whose label contains one of these texts (each keeps the seed it has in the
    whole set, so its rows are the whole run's).
    """
    cases = chosen_cases(quick, held_out, several_surfaces, scenes)
    model = load_model(model_path)
    config = Config()
    rows = []
    for scene_index, (label, factory, edges) in cases:
        scene = factory()  # the geometry does not depend on the footprint: build it once
        for footprint_index, true_m2 in enumerate(QUICK_FOOTPRINTS_M2 if quick else FOOTPRINTS_M2):
            rng = np.random.default_rng([seed, scene_index, footprint_index])
            truth: dict[str, np.ndarray] = {}
            scan = render(scene, config, rng, coupling_gain=coupling_gain(true_m2), truth_out=truth)
            rows.append(measure_row(label, scan, edges, model, true_m2, truth["bias_m"][:, -1].reshape(scan.shape)))
            if on_row is not None:
                on_row(rows[-1])
    return rows


def _mm(value: float) -> str:
    return "" if math.isnan(value) else f"{value:.3f}"


def format_row(row: dict[str, Any]) -> str:
    ratio = row["estimate_m2"] / row["true_m2"]
    cells = [row["scene"], f"{row['true_m2']:g}", _mm(row["raw_mm"]), _mm(row["true_mm"]), _mm(row["auto_mm"]),
             _mm(row["edge_raw_mm"]), _mm(row["edge_true_mm"]), _mm(row["edge_auto_mm"]),
             _mm(row["edge_multipath_mm"]), _mm(row["edge_removed_mm"]),
             f"{row['estimate_m2']:.4g} (+-{row['sigma_m2']:.2g})", f"{ratio:.2f}",
             "yes" if row["significant"] else "no"]
    return "| " + " | ".join(cells) + " |"


def _verdict(met: bool) -> str:
    return "met" if met else "NOT met"


def estimate_factor(row: dict[str, Any]) -> float:
    """max(est / true, true / est); inf where nothing (or nothing positive) was measured."""
    estimate = row["estimate_m2"]
    if not np.isfinite(estimate) or estimate <= 0:
        return float("inf")
    return max(estimate / row["true_m2"], row["true_m2"] / estimate)


def worst(values: list[tuple[float, str]], highest: bool = True) -> tuple[float, str] | None:
    """The worst (value, scene) of a list (the highest, or the lowest), None when empty."""
    if not values:
        return None
    return max(values) if highest else min(values)


def summary_line(number: str, text: str, found: tuple[float, str] | None, target: str,
                 met: Callable[[float], bool], unit: str = "") -> str:
    if found is None:
        return f"{number}. {text}: no rows qualify (n/a)"
    value, where = found
    shown = f"{value:.1f}" if unit == " %" else f"{value:.3f}"
    return f"{number}. {text}: {shown}{unit} ({where}) against {target}: {_verdict(met(value))}"


def summary(rows: list[dict[str, Any]]) -> list[str]:
    """The summary block: each target, the worst row's number, met / NOT met."""
    def name(row: dict[str, Any]) -> str:
        return f"{row['scene']}, A_fp {row['true_m2']:g}"

    harm = worst([(r["auto_mm"] - r["raw_mm"], name(r)) for r in rows])
    edged = [r for r in rows if r["corner"] and not math.isnan(r["edge_raw_mm"])]
    ratio = worst([(r["edge_auto_mm"] / r["edge_true_mm"], name(r)) for r in edged])
    strong = [r for r in edged if r["edge_raw_mm"] > STRONG_EDGE_MM]
    reduction = worst([(1 - r["edge_auto_mm"] / r["edge_raw_mm"], name(r)) for r in strong], highest=False)
    reachable = [r for r in strong if 1 - r["edge_removed_mm"] / r["edge_raw_mm"] >= MIN_EDGE_REDUCTION]
    reached = [r for r in reachable if 1 - r["edge_auto_mm"] / r["edge_raw_mm"] >= MIN_EDGE_REDUCTION]
    factor = worst([(estimate_factor(r), name(r)) for r in edged if r["edge_multipath_mm"] > ESTIMATE_EDGE_MM])
    return [
        summary_line("1", "worst auto - raw MAE", harm, f"<= {MAX_AUTO_HARM_MM} mm",
                     lambda v: v <= MAX_AUTO_HARM_MM, " mm"),
        summary_line("2a", "worst edge auto / edge true A_fp", ratio, f"<= {MAX_EDGE_RATIO:.2f}",
                     lambda v: v <= MAX_EDGE_RATIO),
        summary_line("2b", f"worst edge reduction 1 - auto / raw (edge raw > {STRONG_EDGE_MM:g} mm)",
                     None if reduction is None else (100 * reduction[0], reduction[1]),
                     f">= {100 * MIN_EDGE_REDUCTION:.0f} %", lambda v: v >= 100 * MIN_EDGE_REDUCTION, " %"),
        f"2b'. of the {len(strong)} rows with edge raw > {STRONG_EDGE_MM:g} mm, {len(reachable)} come "
        f"{100 * MIN_EDGE_REDUCTION:.0f} % below raw with the rendered multipath removed exactly (the others hold "
        f"too little multipath beside the noise); auto reaches it on {len(reached)} of those {len(reachable)}",
        summary_line("3", f"worst max(est/true, true/est) on corners with edge multipath > {ESTIMATE_EDGE_MM:g} mm",
                     factor,
                     f"<= {MAX_ESTIMATE_FACTOR}", lambda v: v <= MAX_ESTIMATE_FACTOR),
    ]


def calibration_cost(model_path: str, side: int = 1000, repeats: int = 3) -> list[str]:
    """CPU seconds of correcting a side x side cornered board with ``auto`` and with the footprint ``auto``
    found given (median of ``repeats``), and the share the self-calibration adds.

    Given the same footprint, the two corrections gate and correct the same pixels, so the difference is
    the calibration's own cost; against the default footprint it would also count the pixels a different
    footprint sends through the model.
    """
    from mpi_lidar.simulation.scenes import cornered_board

    model = load_model(model_path)
    scan = render(cornered_board(height=side, width=side), Config(), np.random.default_rng(0), patch_spacing_m=0.05)

    def median_cpu(footprint: float | str) -> tuple[float, Any]:
        runs, corrected = [], None
        for _ in range(repeats):
            started = time.process_time()
            corrected = correct_scan(scan, model, CorrectionOptions(footprint_area_m2=footprint))
            runs.append(time.process_time() - started)
        return float(np.median(runs)), corrected

    auto, corrected = median_cpu("auto")
    estimate = corrected.calibration.area_m2
    given = median_cpu(estimate)[0]
    share = auto / given - 1
    return [f"Correction of a {side} x {side} cornered board: auto {auto:.2f} CPU s, the footprint it found "
            f"({estimate:.3g} m^2 for a true {DEFAULT_FOOTPRINT_AREA_M2:.3g} m^2) given {given:.2f} CPU s "
            f"(median of {repeats}): calibration adds {100 * share:.0f} % against <= 20 %: "
            f"{_verdict(share <= 0.20)}"]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--model", required=True, help="Directory of a trained correction model.")
    scenes = parser.add_mutually_exclusive_group()
    scenes.add_argument("--quick", action="store_true", help="Two scenes at two footprints only (for a test).")
    scenes.add_argument("--held-out", action="store_true",
                        help="The corners kept out of the method's development instead of the main set.")
    scenes.add_argument("--several-surfaces", action="store_true",
                        help="Scenes where more than two surfaces face each other, or a floor seen from a tripod.")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--scene", action="append", default=[], metavar="TEXT",
                        help="Only the scenes whose name contains TEXT (repeatable); same renders as the whole set.")
    parser.add_argument("--cost", action="store_true",
                        help="Only the CPU time the calibration adds to correcting a 1000 x 1000 scan.")
    args = parser.parse_args()
    if args.cost:
        print("\n".join(calibration_cost(args.model)))
        return
    print(f"Machine: {platform.node()} ({platform.machine()}), {date.today()}; model {args.model}, "
          f"seed {args.seed}{', quick' if args.quick else ''}{', held-out corners' if args.held_out else ''}"
          f"{', several surfaces' if args.several_surfaces else ''}"
          f"{''.join(f', scenes named like {text!r}' for text in args.scene)}\n")
    try:
        chosen_cases(args.quick, args.held_out, args.several_surfaces, tuple(args.scene))
    except ValueError as error:
        parser.exit(2, f"benchmarks.calibration: {error}\n")
    print(HEADER, flush=True)
    start = time.perf_counter()
    rows = run(args.model, args.quick, args.seed, args.held_out, several_surfaces=args.several_surfaces,
               scenes=tuple(args.scene), on_row=lambda row: print(format_row(row), flush=True))
    print("\nSummary:\n")
    print("\n".join(summary(rows)))
    print(f"\nWall time: {time.perf_counter() - start:.0f} s for {len(rows)} rows")


if __name__ == "__main__":
    main()
