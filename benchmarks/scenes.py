"""Correction on the scene set: does it help where multipath exists and do no harm where it cannot?

Run: .venv/bin/python -m benchmarks.scenes --model DIR [--model DIR ...] [--gate geometry --gate all]
     [--min-bias-mm 1.0 ...] [--seed 0] [--matched-footprint]
 or: .venv/bin/python -m benchmarks.scenes --estimation-error  (geometric estimates against the renderer's)
Renders every scene of :func:`scene_set` once (Table I noise, seeded by the scene's position), corrects it
with each model, gate and geometry-gate threshold, and prints one markdown row per combination: MAE of
the 31.25 MHz depth before/after on the whole map, on the reference mask and, for corners, within 20 cm
of the corner edge, plus the share of valid pixels inside the model's d_AS range that the gate left as
measured ("gated out"; pixels outside that range always keep their raw depth). With ``--matched-footprint``
the external imports are corrected with ``footprint_area_m2`` = 90 pi r^2 for their own footprint radius r
(the calibrated gain of the default) instead of the default footprint. Models trained with geometric inputs
get the gate's rho_ABA and d_AB estimates for the pixels they correct.
"""

from __future__ import annotations

import argparse
import platform
from collections.abc import Callable
from datetime import date

import numpy as np

from mpi_lidar.config import Config
from mpi_lidar.correction import GATES, INVALID_FLAGS, CorrectionOptions, Flag, analyse_geometry, correct_scan
from mpi_lidar.learning.model import load_model
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
    scan_from_phasors,
    sphere_scene,
    wooden_corner,
)

EDGE_RADIUS_M = 0.2


EdgeLine = tuple[np.ndarray, np.ndarray]  # a point on a corner's edge and the edge's unit direction


def edge_line(distance: float, roll_deg: float = 0.0) -> EdgeLine:
    """The edge of a corner ``distance`` away on the view's axis, vertical unless rolled by ``roll_deg``."""
    roll = np.deg2rad(roll_deg)
    return np.array([0.0, 0.0, distance]), np.array([-np.sin(roll), np.cos(roll), 0.0])


def scene_set() -> list[tuple[str, Callable[[], Scene], EdgeLine | None]]:
    """(label, scene factory, the corner's edge line or None) of the evaluation set."""
    scenes: list[tuple[str, Callable[[], Scene], EdgeLine | None]] = [
        (f"flat wall {tilt} deg", lambda tilt=tilt: flat_wall(float(tilt)), None) for tilt in (0, 30, 60)]
    scenes += [("cylinder", cylinder_scene, None), ("sphere", sphere_scene, None)]
    for angle, distance, albedo in ((60, 2.0, 0.8), (90, 2.0, 0.8), (120, 2.0, 0.8), (90, 1.8, 0.8),
                                    (90, 2.3, 0.8), (90, 2.0, 0.3)):
        scenes.append((f"corner {angle} deg, {distance} m, albedo {albedo}",
                       lambda a=angle, d=distance, r=albedo: corner(float(a), d, r), edge_line(distance)))
    scenes += [("cornered board (Fig. 7)", cornered_board, edge_line(2.25)),
               ("wooden corner (Fig. 10)", wooden_corner, edge_line(2.3)),
               ("multi-object (Fig. 8)", multi_object, None)]
    return scenes


# footprint_area_m2 of a sensor with footprint radius r: this gain times pi r^2 (physics.coupling.footprint_area).
MATCHED_FOOTPRINT_GAIN = DEFAULT_COUPLING_GAIN


def external_corner(footprint_radius_m: float, config: Config, rng: np.random.Generator) -> Scan:
    """A 90-degree corner whose correlation phasors are imported through :func:`scan_from_phasors`, the
    path an external transient renderer takes (here the phasors come from our own light transport)."""
    scene = corner(90.0, 2.0, 0.8)
    reference = render(scene, config.replace(simulator={"noise_scale": 0.0}), np.random.default_rng(0))
    phasor, dc = light_transport(scene, config, footprint_radius_m, 0.02, DEFAULT_COUPLING_GAIN)
    h, w = reference.shape
    return scan_from_phasors(f"external_fp{footprint_radius_m * 1e3:g}mm", phasor.T.reshape(-1, h, w), config,
                             rng, dc_gamma=dc.T.reshape(-1, h, w), azimuth_rad=scene.azimuth_rad,
                             elevation_rad=scene.elevation_rad, reference_depth=reference.reference_depth,
                             reference_mask=reference.reference_mask)


def edge_line_region(scan: Scan, edge: EdgeLine) -> np.ndarray:
    """Pixels whose true surface point lies within EDGE_RADIUS_M of the corner's edge line."""
    point, direction = edge
    offsets = scan.reference_depth[..., None] * scan.rays() - point
    across = offsets - (offsets @ direction)[..., None] * direction
    return np.linalg.norm(across, axis=-1) <= EDGE_RADIUS_M


def mae_mm(values: np.ndarray, reference: np.ndarray, where: np.ndarray) -> float:
    return float(1e3 * np.abs(values[where] - reference[where]).mean()) if where.any() else float("nan")


def estimation_error(config: Config, seed: int) -> None:
    """How well the scan's geometry estimates the renderer's true coupling, equivalent rho_ABA (a correction
    model's input) and d_AB, from the noisy raw depth and amplitude."""
    print("| scene | estimate / true coupling, median (IQR) | estimate / true equivalent rho_ABA, median (IQR) "
          "| d_AB error [cm], median (sd) | the blocks' rho_ABA / true, median (IQR) | their d_AB error [cm] "
          "| pixels |")
    print("|---|---|---|---|---|---|---|")
    options = CorrectionOptions(footprint_area_m2=DEFAULT_FOOTPRINT_AREA_M2)
    for index, (label, factory, _) in enumerate(scene_set()):
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


def quartiles(values: np.ndarray) -> str:
    """'median (first-third quartile)' of ``values``, two decimals."""
    q1, q2, q3 = np.quantile(values, [0.25, 0.5, 0.75])
    return f"{q2:.2f} ({q1:.2f}-{q3:.2f})"


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
    args = parser.parse_args()
    if args.estimation_error:
        estimation_error(Config(), args.seed)
        return
    if not args.model:
        parser.error("give at least one --model (or --estimation-error)")
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
    items: list[tuple[str, Scan, EdgeLine | None, float | None]] = []
    for index, (label, factory, edge) in enumerate(scene_set()):
        items.append((label, render(factory(), config, np.random.default_rng([args.seed, index])), edge, None))
    for k, radius in enumerate((0.004, DEFAULT_FOOTPRINT_RADIUS_M * 2)):
        scan = external_corner(radius, config, np.random.default_rng([args.seed, 100 + k]))
        area = footprint_area(radius, MATCHED_FOOTPRINT_GAIN) if args.matched_footprint else None
        items.append((f"external corner 90 deg, footprint {radius * 1e3:g} mm", scan, edge_line(2.0), area))
    for label, scan, edge, footprint_area_m2 in items:
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
