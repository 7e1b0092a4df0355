"""Correction on the scene set: does it help where multipath exists and do no harm where it cannot?

Run: .venv/bin/python -m benchmarks.scenes --model DIR [--model DIR ...] [--gate geometry --gate all]
     [--min-bias-mm 1.0 ...] [--seed 0] [--matched-footprint]
 or: .venv/bin/python -m benchmarks.scenes --estimation-error  (geometric estimates against the renderer's,
     per scene and by true d_AB)
 or: .venv/bin/python -m benchmarks.scenes --baselines --model DIR  (the fused baseline against the raw one)
Renders every scene of :func:`scene_set` once (Table I noise, seeded by the scene's position), corrects it
with each model, gate and geometry-gate threshold, and prints one markdown row per combination: MAE of
the 31.25 MHz depth before/after on the whole map, on the reference mask and, for corners, within 20 cm
of the corner edge, plus the share of valid pixels inside the model's d_AS range that the gate left as
measured ("gated out"; pixels outside that range always keep their raw depth). With ``--matched-footprint``
the external imports are corrected with ``footprint_area_m2`` = 90 pi r^2 for their own footprint radius r
(the calibrated gain of the default) instead of the default footprint. Models trained with geometric inputs
get the gate's rho_ABA and d_AB estimates for the pixels they correct.

``--baselines`` corrects every scene with default options twice, with ``--baseline raw`` (pixels the model does
not correct keep the highest frequency's depth) and with the default fused baseline, and prints per scene the
MAE of both on the whole map, the reference mask and at the edge, whether the fused one is no worse (whole map
and mask), the share of valid pixels per estimate (measured, fused, corrected) and the share of pixels whose
error lies within their 1-sigma uncertainty. ``--shrink N`` divides every scene's height and width by N (a quick
look, a test).
"""

from __future__ import annotations

import argparse
import platform
import time
from collections.abc import Callable
from dataclasses import dataclass
from datetime import date

import numpy as np

from mpi_lidar.config import Config
from mpi_lidar.correction import GATES, INVALID_FLAGS, CorrectionOptions, Flag, analyse_geometry, correct_scan
from mpi_lidar.correction.options import Baseline, Estimate
from mpi_lidar.correction.result import Correction
from mpi_lidar.learning.model import CorrectionModel, load_model
from mpi_lidar.physics.coupling import DEFAULT_FOOTPRINT_AREA_M2, footprint_area
from mpi_lidar.scans.scan import Scan
from mpi_lidar.simulation.scenes import (
    DEFAULT_COUPLING_GAIN,
    DEFAULT_FOOTPRINT_RADIUS_M,
    Scene,
    corner,
    cornered_board,
    cylinder_scene,
    flat_wall,
    light_transport,
    multi_object,
    render,
    room_with_box,
    scan_from_phasors,
    sphere_scene,
    turned_room_with_box,
    wooden_corner,
)

EDGE_RADIUS_M = 0.2


EdgeLine = tuple[np.ndarray, np.ndarray]  # a point on a corner's edge and the edge's unit direction


def edge_line(distance: float, roll_deg: float = 0.0) -> EdgeLine:
    """The edge of a corner ``distance`` away on the view's axis, vertical unless rolled by ``roll_deg``."""
    roll = np.deg2rad(roll_deg)
    return np.array([0.0, 0.0, distance]), np.array([-np.sin(roll), np.cos(roll), 0.0])


def scene_set(shrink: int = 1) -> list[tuple[str, Callable[[], Scene], EdgeLine | None]]:
    """(label, scene factory, the corner's edge line or None) of the evaluation set, each scene's height and
    width divided by ``shrink`` (same field of view, fewer pixels)."""
    small, large = {"height": 96 // shrink, "width": 128 // shrink}, {"height": 120 // shrink, "width": 160 // shrink}
    scenes: list[tuple[str, Callable[[], Scene], EdgeLine | None]] = [
        (f"flat wall {tilt} deg", lambda tilt=tilt: flat_wall(float(tilt), **small), None) for tilt in (0, 30, 60)]
    scenes += [("cylinder", lambda: cylinder_scene(**small), None), ("sphere", lambda: sphere_scene(**small), None)]
    for angle, distance, albedo in ((60, 2.0, 0.8), (90, 2.0, 0.8), (120, 2.0, 0.8), (90, 1.8, 0.8),
                                    (90, 2.3, 0.8), (90, 2.0, 0.3)):
        scenes.append((f"corner {angle} deg, {distance} m, albedo {albedo}",
                       lambda a=angle, d=distance, r=albedo: corner(float(a), d, r, **small), edge_line(distance)))
    scenes += [("cornered board (Fig. 7)", lambda: cornered_board(**large), edge_line(2.25)),
               ("wooden corner (Fig. 10)", lambda: wooden_corner(**small), edge_line(2.3)),
               ("multi-object (Fig. 8)", lambda: multi_object(**large), None)]
    return scenes + room_set(shrink)


# The rooms' effective receiver footprints [m^2]: weak, middling and strong coupling (the default is 0.041).
ROOM_FOOTPRINTS_M2 = (0.002, 0.024, 0.073)


def room_set(shrink: int = 1) -> list[tuple[str, Callable[[], Scene], EdgeLine | None]]:
    """The two room corners (multi-bounce light transport, a box on the floor) at each of ROOM_FOOTPRINTS_M2, each
    with its vertical wall-wall fold as its edge line; the rooms' other folds and tri-corners are on the scene
    (:attr:`Scene.folds`, :attr:`Scene.tri_corners`)."""
    rooms: list[tuple[str, Callable[[], Scene], EdgeLine | None]] = []
    for name, factory, (height, width) in ROOMS:
        for area in ROOM_FOOTPRINTS_M2:
            def make(f: Callable[..., Scene] = factory, a: float = area, h: int = height, w: int = width) -> Scene:
                return f(height=h // shrink, width=w // shrink, footprint_m2=a)
            rooms.append((f"{name}, footprint {area:g} m^2", make, vertical_fold(make())))
    return rooms


# The rooms and their scan grids (height, width): the turned room's wider view needs more pixels, or its floor
# and ceiling are too few blocks across for the geometry stage's planes.
ROOMS: tuple[tuple[str, Callable[..., Scene], tuple[int, int]], ...] = (
    ("room corner", room_with_box, (48, 64)), ("turned room corner with ceiling", turned_room_with_box, (72, 96)))


def vertical_fold(scene: Scene) -> EdgeLine:
    """The edge line through a room's first fold after its floor's two (the walls' vertical one)."""
    start, end = (np.asarray(point) for point in scene.folds[2])
    return start, (end - start) / np.linalg.norm(end - start)


# footprint_area_m2 of a sensor with footprint radius r: this gain times pi r^2 (physics.coupling.footprint_area).
MATCHED_FOOTPRINT_GAIN = DEFAULT_COUPLING_GAIN


def external_corner(footprint_radius_m: float, config: Config, rng: np.random.Generator, shrink: int = 1) -> Scan:
    """A 90-degree corner whose correlation phasors are imported through :func:`scan_from_phasors`, the
    path an external transient renderer takes (here the phasors come from our own light transport)."""
    scene = corner(90.0, 2.0, 0.8, 96 // shrink, 128 // shrink)
    reference = render(scene, config.replace(simulator={"noise_scale": 0.0}), np.random.default_rng(0))
    phasor, dc = light_transport(scene, config, footprint_radius_m, 0.02, DEFAULT_COUPLING_GAIN)
    h, w = reference.shape
    return scan_from_phasors(f"external_fp{footprint_radius_m * 1e3:g}mm", phasor.T.reshape(-1, h, w), config,
                             rng, dc_gamma=dc.T.reshape(-1, h, w), azimuth_rad=scene.azimuth_rad,
                             elevation_rad=scene.elevation_rad, reference_depth=reference.reference_depth,
                             reference_mask=reference.reference_mask)


# (label, scan, its corner's edge line or None, the footprint area to correct it with [m^2] or None: the default)
Item = tuple[str, Scan, EdgeLine | None, float | None]


def rendered_items(config: Config, seed: int, matched_footprint: bool = False, shrink: int = 1) -> list[Item]:
    """Every scene of :func:`scene_set`, rendered (seeded by its position), then the two external imports."""
    items: list[Item] = []
    for index, (label, factory, edge) in enumerate(scene_set(shrink)):
        items.append((label, render(factory(), config, np.random.default_rng([seed, index])), edge, None))
    for k, radius in enumerate((0.004, DEFAULT_FOOTPRINT_RADIUS_M * 2)):
        scan = external_corner(radius, config, np.random.default_rng([seed, 100 + k]), shrink)
        area = footprint_area(radius, MATCHED_FOOTPRINT_GAIN) if matched_footprint else None
        items.append((f"external corner 90 deg, footprint {radius * 1e3:g} mm", scan, edge_line(2.0), area))
    return items


def edge_line_region(scan: Scan, edge: EdgeLine) -> np.ndarray:
    """Pixels whose true surface point lies within EDGE_RADIUS_M of the corner's edge line."""
    point, direction = edge
    offsets = scan.reference_depth[..., None] * scan.rays() - point
    across = offsets - (offsets @ direction)[..., None] * direction
    return np.linalg.norm(across, axis=-1) <= EDGE_RADIUS_M


def mae_mm(values: np.ndarray, reference: np.ndarray, where: np.ndarray) -> float:
    return float(1e3 * np.abs(values[where] - reference[where]).mean()) if where.any() else float("nan")


def estimation_error(config: Config, seed: int, shrink: int = 1) -> None:
    """How well the scan's geometry estimates the renderer's true coupling, equivalent rho_ABA (a correction
    model's input) and d_AB, from the noisy raw depth and amplitude: a row per scene, then the d_AB error of all
    scenes' pixels by their true d_AB (:func:`print_distance_error`)."""
    print("| scene | estimate / true coupling, median (IQR) | estimate / true equivalent rho_ABA, median (IQR) "
          "| d_AB error [cm], median (sd) | the blocks' rho_ABA / true, median (IQR) | their d_AB error [cm] "
          "| pixels |")
    print("|---|---|---|---|---|---|---|")
    options = CorrectionOptions(footprint_area_m2=DEFAULT_FOOTPRINT_AREA_M2)
    pooled: list[np.ndarray] = []  # (true d_AB, estimated d_AB) [m] of every scene's pixels
    for index, (label, factory, _) in enumerate(scene_set(shrink)):
        truth: dict[str, np.ndarray] = {}
        scan = render(factory(), config, np.random.default_rng([seed, index]), truth_out=truth)
        depth_top = np.where(np.isfinite(scan.reference_depth), scan.depth[-1], np.nan)  # sky: no return
        scene = analyse_geometry(scan, depth_top.ravel(), options, config.sensor, with_model_inputs=True)
        potential = scene.potential.rows()
        inputs = scene.model_inputs
        rho_aba, d_ab = inputs.pixels(np.arange(depth_top.size), depth_top.ravel())
        block_rho_aba, block_d_ab = inputs.fallback.pixels(np.arange(depth_top.size))
        true = truth["coupling"].reshape(scan.shape)
        where = (true > 0.005) & (true < 0.9)
        if not where.any():
            print(f"| {label} | no true coupling above 0.005; estimate max {potential.coupling.max():.3g} | "
                  f"estimate max {rho_aba.max():.3g} | | estimate max {block_rho_aba.max():.3g} | | 0 |")
            continue
        flat = where.ravel()
        coupling_ratio = potential.coupling[where] / true[where]
        rho_ratio = rho_aba[flat] / truth["rho_aba"][flat]
        error = 100 * (d_ab[flat] - truth["d_ab_m"][flat])
        block_ratio = block_rho_aba[flat] / truth["rho_aba"][flat]
        block_error = 100 * (block_d_ab[flat] - truth["d_ab_m"][flat])
        print(f"| {label} | {quartiles(coupling_ratio)} | {quartiles(rho_ratio)} | {np.nanmedian(error):.1f} "
              f"({np.nanstd(error):.1f}) | {quartiles(block_ratio)} | {np.nanmedian(block_error):.1f} "
              f"({np.nanstd(block_error):.1f}) | {int(where.sum())} |", flush=True)
        pooled.append(np.column_stack([truth["d_ab_m"][flat], d_ab[flat]]))
    print_distance_error(np.concatenate(pooled) if pooled else np.zeros((0, 2)))


# Bins of the true d_AB [m] the pooled d_AB error is told in (lower edges; the last is open).
DISTANCE_BINS_M = (0.0, 0.05, 0.1, 0.2, 0.3, 0.45, 0.6)


def print_distance_error(pairs: np.ndarray) -> None:
    """The d_AB estimate's error by true d_AB, from pairs (n, 2) of true and estimated d_AB [m]: per bin, the
    median, a robust sd (half the 16-84 % spread, which a few wrong partners do not blow up) and the share of
    pixels more than 2 cm off, in cm and %."""
    print("\n| true d_AB [m] | d_AB error [cm], median | robust sd [cm] | off by > 2 cm [%] | pixels |")
    print("|---|---|---|---|---|")
    finite = pairs[np.isfinite(pairs).all(axis=1)]
    uppers = (*DISTANCE_BINS_M[1:], np.inf)
    for lower, upper in zip(DISTANCE_BINS_M, uppers, strict=True):
        error = 100 * np.diff(finite[(finite[:, 0] >= lower) & (finite[:, 0] < upper)], axis=1).ravel()
        told = f"{lower:g}-{upper:g}" if np.isfinite(upper) else f"{lower:g}+"
        if error.size == 0:
            print(f"| {told} | | | | 0 |")
            continue
        low, median, high = np.quantile(error, [0.16, 0.5, 0.84])
        print(f"| {told} | {median:.2f} | {(high - low) / 2:.2f} | {100 * np.mean(np.abs(error) > 2):.1f} "
              f"| {error.size} |")


def quartiles(values: np.ndarray) -> str:
    """'median (first-third quartile)' of ``values``, two decimals."""
    q1, q2, q3 = np.quantile(values, [0.25, 0.5, 0.75])
    return f"{q2:.2f} ({q1:.2f}-{q3:.2f})"


BASELINE_HEADER = ("| scene | whole map, raw / fused baseline [mm] | masked, raw / fused baseline [mm] "
                   "| change, whole / masked | fused <= raw | edge, raw / fused baseline [mm] "
                   "| measured / fused / corrected [%] | within 1 sigma [%] |\n|---|---|---|---|---|---|---|---|")
REGIONS = ("whole map", "masked", "edge")


@dataclass(frozen=True)
class BaselineComparison:
    """A scene corrected with default options under the raw and under the fused baseline.

    ``mae_mm`` maps each of REGIONS to the MAE [mm] of the output depth under the raw and the fused baseline, on
    the pixels valid in both runs: all of them, those in the reference mask, those within EDGE_RADIUS_M of the
    corner's edge line (NaN where a region has no pixel: convex scenes have no mask, flat ones no edge);
    ``shares`` the fused run's valid pixels per estimate (measured, fused, corrected) [1]; ``covered`` the share
    of its valid pixels whose error is at most their 1-sigma uncertainty [1].
    """

    mae_mm: dict[str, tuple[float, float]]
    shares: dict[str, float]
    covered: float

    @property
    def fused_no_worse(self) -> bool:
        """Fused MAE <= raw MAE on the whole map and, where the scene has one, on the mask."""
        whole, masked = self.mae_mm["whole map"], self.mae_mm["masked"]
        return whole[1] <= whole[0] and (not np.isfinite(masked[0]) or masked[1] <= masked[0])


def valid_pixels(scan: Scan, run: Correction) -> np.ndarray:
    """Pixels with a reference depth and a valid output depth."""
    assert scan.reference_depth is not None
    invalid = np.isin(run.flags, [int(f) for f in INVALID_FLAGS])
    return np.isfinite(scan.reference_depth) & np.isfinite(run.depth) & ~invalid


def estimate_shares(run: Correction) -> dict[str, float]:
    """Share of the valid pixels (those with an estimate) per estimate: measured, fused, corrected [1]."""
    counts = run.estimate_counts()
    names = [e.name.lower() for e in Estimate if e != Estimate.NONE]
    total = sum(counts.get(name, 0) for name in names)
    return {name: counts.get(name, 0) / total if total else float("nan") for name in names}


def covered_share(run: Correction, reference: np.ndarray, where: np.ndarray) -> float:
    """Share of the pixels ``where`` with an uncertainty whose error is at most their 1-sigma uncertainty [1]."""
    if run.uncertainty_m is None:
        return float("nan")
    sigma = run.uncertainty_m.astype(np.float64)
    where = where & np.isfinite(sigma)
    error = np.abs(run.depth.astype(np.float64) - reference)
    return float((error[where] <= sigma[where]).mean()) if where.any() else float("nan")


def compare_baselines(scan: Scan, model: CorrectionModel, edge: EdgeLine | None) -> BaselineComparison:
    """Correct ``scan`` with default options, once with ``--baseline raw``, and compare the two on one pixel set."""
    assert scan.reference_depth is not None and scan.reference_mask is not None
    raw_run = correct_scan(scan, model, CorrectionOptions(baseline=Baseline.RAW))
    fused_run = correct_scan(scan, model)
    usable = valid_pixels(scan, raw_run) & valid_pixels(scan, fused_run)
    near = edge_line_region(scan, edge) if edge is not None else np.zeros_like(usable)
    regions = dict(zip(REGIONS, (usable, usable & scan.reference_mask, usable & near), strict=True))
    reference = scan.reference_depth
    mae = {name: (mae_mm(raw_run.depth, reference, where), mae_mm(fused_run.depth, reference, where))
           for name, where in regions.items()}
    return BaselineComparison(mae, estimate_shares(fused_run), covered_share(fused_run, reference, usable))


def baseline_rows(model: CorrectionModel, items: list[Item]) -> list[tuple[str, BaselineComparison]]:
    """One comparison per scene. The items' footprint areas are not used: default options calibrate their own."""
    return [(label, compare_baselines(scan, model, edge)) for label, scan, edge, _ in items]


def format_baseline_row(label: str, row: BaselineComparison) -> str:
    pairs = {name: f"{_cell(raw)} / {_cell(fused)}" if np.isfinite(raw) else "" for name, (raw, fused) in
             row.mae_mm.items()}
    change = " / ".join(_cell(100 * (fused / raw - 1), "+.1f") + " %" if np.isfinite(raw) else "-"
                        for raw, fused in (row.mae_mm["whole map"], row.mae_mm["masked"]))
    shares = " / ".join(f"{100 * row.shares[name]:.1f}" for name in ("measured", "fused", "corrected"))
    return (f"| {label} | {pairs['whole map']} | {pairs['masked']} | {change} "
            f"| {'yes' if row.fused_no_worse else '**no**'} | {pairs['edge']} | {shares} "
            f"| {_cell(100 * row.covered, '.1f')} |")


def _cell(value: float, spec: str = ".3f") -> str:
    return "" if not np.isfinite(value) else format(value, spec)


def print_baselines(model_paths: list[str], seed: int, shrink: int) -> None:
    """The --baselines table of each model, with how many scenes met "fused <= raw" on the mask."""
    started = time.perf_counter()
    items = rendered_items(Config(), seed, shrink=shrink)
    for path in model_paths:
        model = load_model(path)
        print(f"model {path} ({model.booster.num_boosted_rounds()} trees, {model.spec.feature_set} inputs"
              f"{', geometric' if model.geometric else ''}): default options against --baseline raw; "
              f"Table I noise, seed {seed}\n")
        print(BASELINE_HEADER)
        rows = baseline_rows(model, items)
        for label, row in rows:
            print(format_baseline_row(label, row), flush=True)
        met = sum(row.fused_no_worse for _, row in rows)
        print(f"\nfused <= raw (whole map and mask): {met} of {len(rows)} scenes\n")
    print(f"{platform.system()}, {platform.machine()}, Python {platform.python_version()}, {date.today()}, "
          f"{time.perf_counter() - started:.0f} s wall")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--model", action="append")
    parser.add_argument("--estimation-error", action="store_true",
                        help="Only compare the geometric coupling estimate with the renderer's truth.")
    parser.add_argument("--gate", action="append", choices=GATES)
    parser.add_argument("--min-bias-mm", action="append", type=float)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--matched-footprint", action="store_true",
                        help="Correct the external imports with the footprint area of their own footprint.")
    parser.add_argument("--baselines", action="store_true",
                        help="Only compare the default fused baseline with --baseline raw, default options.")
    parser.add_argument("--shrink", type=int, default=1,
                        help="With --baselines or --estimation-error: divide every scene's height and width by "
                             "this (a quick look).")
    args = parser.parse_args()
    if args.estimation_error:
        estimation_error(Config(), args.seed, args.shrink)
        return
    if not args.model:
        parser.error("give at least one --model (or --estimation-error)")
    if args.baselines:
        print_baselines(args.model, args.seed, args.shrink)
        return
    gates = args.gate or ["geometry", "all"]
    thresholds = args.min_bias_mm or [1e3 * CorrectionOptions().min_multipath_bias_m]
    config = Config()
    models = {path: load_model(path) for path in args.model}
    print(f"Machine: {platform.node()} ({platform.machine()}), {date.today()}; models "
          + ", ".join(f"{p} ({m.booster.num_boosted_rounds()} trees, prior {m.card.dataset.prior.model_dump()})"
                      for p, m in models.items()) + "\n")
    print("| scene | model | gate | min bias [mm] | gated out | raw MAE [mm] | corrected MAE [mm] | masked raw "
          "[mm] | masked corrected [mm] | edge raw [mm] | edge corrected [mm] | gate ms |")
    print("|---|---|---|---|---|---|---|---|---|---|---|---|")
    for label, scan, edge, footprint_area_m2 in rendered_items(config, args.seed, args.matched_footprint):
        for path, model in models.items():
            for gate in gates:
                for threshold in (thresholds if gate == "geometry" else [float("nan")]):
                    # The footprint the renders were made with (or the imports' own): docs/results/scenes.md
                    footprint = footprint_area_m2 or DEFAULT_FOOTPRINT_AREA_M2
                    bias = {"min_multipath_bias_m": threshold / 1e3} if gate == "geometry" else {}
                    options = CorrectionOptions(gate=gate, footprint_area_m2=footprint, **bias)
                    correction = correct_scan(scan, model, options)
                    usable = ~np.isin(correction.flags, [int(f) for f in INVALID_FLAGS])
                    usable &= np.isfinite(scan.reference_depth)
                    in_range = usable & (correction.flags != Flag.OUT_OF_RANGE)
                    gated = np.isin(correction.flags, [Flag.NOT_NEEDED, Flag.NO_MULTIPATH])[in_range].mean()
                    raw, ref = scan.depth[-1], scan.reference_depth
                    masked = usable & scan.reference_mask
                    near = usable & edge_line_region(scan, edge) if edge is not None else np.zeros_like(usable)
                    cells = [label, path.rstrip("/").split("/")[-1], gate,
                             f"{threshold:g}" if gate == "geometry" else "", f"{100 * gated:.1f} %",
                             f"{mae_mm(raw, ref, usable):.3f}", f"{mae_mm(correction.depth, ref, usable):.3f}",
                             f"{mae_mm(raw, ref, masked):.3f}", f"{mae_mm(correction.depth, ref, masked):.3f}",
                             f"{mae_mm(raw, ref, near):.3f}" if edge is not None else "",
                             f"{mae_mm(correction.depth, ref, near):.3f}" if edge is not None else "",
                             f"{1e3 * correction.gate_s:.0f}"]
                    print("| " + " | ".join(cells) + " |", flush=True)


if __name__ == "__main__":
    main()
