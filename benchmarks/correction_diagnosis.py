"""Where the correction model falls short of the multipath, pixel by pixel, with the true footprint given.

Run: .venv/bin/python -m benchmarks.correction_diagnosis --model DIR [--quick] [--seed 0]
Renders scenes at one true footprint A_fp, corrects each with that footprint (so the calibration plays no
part) and sorts the pixels near the scene's edges by the render's own noise-free multipath bias of the
31.25 MHz depth into five bins (quartiles and the top tenth). Per bin it prints the incidence cosine of the
beam on the true surface, the render's true equivalent rho_ABA and A-B distance against the scan's estimates
(the model's geometric inputs), the true bias, what the correction took off, and what the same model takes
off when fed the render's true rho_ABA and d_AB instead of the estimates (a question asked of the model, not
something correction does): the gap between the last two is the estimates' error, the gap between the last
and the true bias the model's own. ``--quick`` runs one small corner (for a test).
"""

from __future__ import annotations

import argparse
import platform
import time
from datetime import date
from typing import Any

import numpy as np

from benchmarks.calibration import (
    SEVERAL_SURFACES,
    SHAPED_CORNERS,
    corner_case,
    coupling_gain,
    near_edges,
    shaped_cases,
    usable_pixels,
)
from benchmarks.scenes import EdgeLine, edge_line
from mpi_lidar.config import Config, SensorConfig
from mpi_lidar.correction import MODEL_FLAGS, CorrectionOptions, analyse_geometry, correct_scan
from mpi_lidar.learning.features import geometry_inputs
from mpi_lidar.learning.model import CorrectionModel, load_model
from mpi_lidar.scans.geometry import surface_normals
from mpi_lidar.scans.scan import Scan
from mpi_lidar.simulation.scenes import Scene, corner, render

TRUE_FOOTPRINT_M2 = 0.041
# Bin edges as quantiles of the true bias over the pixels near the edges: four quartiles and the top tenth.
BIN_QUANTILES = (0.0, 0.25, 0.5, 0.75, 0.9, 1.0)

HEADER = ("| scene | true bias [mm] | pixels | cos_i | rho_ABA true / est. | d_AB true / est. [m] "
          "| mean true bias [mm] | taken off [mm] | taken off, true rho_ABA and d_AB [mm] |\n" + "|---" * 9 + "|")


def diagnosis_cases(quick: bool) -> list[tuple[str, Scene, tuple[EdgeLine, ...]]]:
    """The scenes: corners of the calibration's main set (narrow and bright, near and bright, far and grey, and
    the two of two albedos) and the room's corner and the alcove."""
    if quick:
        return [("corner 60 deg, 2 m, albedo 0.8", corner(60.0, 2.0, 0.8, height=48, width=64), (edge_line(2.0),))]
    corners = [corner_case(60, 2.4, 0.9), corner_case(90, 1.4, 0.9), corner_case(90, 2.4, 0.5)]
    two_albedos = [case for case in shaped_cases(SHAPED_CORNERS) if "/" in case[0]]
    chosen = [*corners, *two_albedos, *SEVERAL_SURFACES[:2]]
    return [(label, factory(), edges) for label, factory, edges in chosen]


def incidence_cosine(scan: Scan) -> np.ndarray:
    """|cos| of the beam on the true surface per pixel (H, W), from the reference depth's points (NaN where a
    neighbour has no reference point)."""
    rays = scan.rays()
    normals = surface_normals(rays * scan.reference_depth[..., None])
    return np.abs((normals * rays).sum(-1))


def diagnose(label: str, scene: Scene, edges: tuple[EdgeLine, ...], model: CorrectionModel, seed: int,
             true_m2: float = TRUE_FOOTPRINT_M2) -> list[dict[str, Any]]:
    """One row per bin of true bias over the corrected pixels near ``edges`` (see the module's docstring);
    none where the correction left too few of them."""
    truth: dict[str, np.ndarray] = {}
    scan = render(scene, Config(), np.random.default_rng(seed), coupling_gain=coupling_gain(true_m2),
                  truth_out=truth)
    options = CorrectionOptions(footprint_area_m2=true_m2)
    correction = correct_scan(scan, model, options)
    raw = scan.raw_pixels()
    f = len(scan.frequencies_hz)
    usable = usable_pixels(scan, correction.flags)
    geometry = analyse_geometry(scan, np.where(usable.ravel(), raw[:, f - 1], np.nan), options, SensorConfig(),
                                with_model_inputs=True)
    chosen = np.flatnonzero((usable & near_edges(scan, edges)).ravel()
                            & np.isin(correction.flags.ravel(), MODEL_FLAGS))
    if chosen.size < len(BIN_QUANTILES):
        return []  # the gate left the edges as measured: nothing to take apart
    cos_i = incidence_cosine(scan).ravel()[chosen]
    inputs = geometry_inputs(*geometry.model_inputs.pixels(chosen, raw[chosen, f - 1]))
    exact = geometry_inputs(truth["rho_aba"][chosen], truth["d_ab_m"][chosen])
    measured = raw[chosen, f - 1]
    per_pixel = {"cos_i": cos_i, "bias_m": truth["bias_m"][chosen, -1],
                 "rho_aba": np.column_stack([exact[:, 0], inputs[:, 0]]),
                 "d_ab_m": np.column_stack([exact[:, 1], inputs[:, 1]]),
                 "taken_off_m": measured - correction.depth.ravel()[chosen],
                 "exact_inputs_m": measured - model.predict_depth(raw[chosen], exact)}
    return bin_rows(label, per_pixel)


def bin_rows(label: str, per_pixel: dict[str, np.ndarray]) -> list[dict[str, Any]]:
    """The rows of :func:`diagnose`: per-pixel values (n,) or true / estimated pairs (n, 2), summarised per bin
    of the true bias ``bias_m``."""
    bias = per_pixel["bias_m"]
    bins = np.searchsorted(np.quantile(bias, BIN_QUANTILES)[1:-1], bias, side="right")
    rows = []
    for index in range(len(BIN_QUANTILES) - 1):
        inside = bins == index
        rows.append({"scene": label, "bin_mm": (1e3 * bias[inside].min(), 1e3 * bias[inside].max()),
                     "pixels": int(inside.sum()), "cos_i": float(np.nanmedian(per_pixel["cos_i"][inside])),
                     "rho_aba": tuple(np.nanmedian(per_pixel["rho_aba"][inside], axis=0)),
                     "d_ab_m": tuple(np.nanmedian(per_pixel["d_ab_m"][inside], axis=0)),
                     "bias_mm": float(1e3 * bias[inside].mean()),
                     "taken_off_mm": float(1e3 * per_pixel["taken_off_m"][inside].mean()),
                     "exact_inputs_mm": float(1e3 * per_pixel["exact_inputs_m"][inside].mean())})
    return rows


def format_row(row: dict[str, Any]) -> str:
    low, high = row["bin_mm"]
    return (f"| {row['scene']} | {low:.1f}-{high:.1f} | {row['pixels']} | {row['cos_i']:.2f} "
            f"| {row['rho_aba'][0]:.3f} / {row['rho_aba'][1]:.3f} | {row['d_ab_m'][0]:.3f} / {row['d_ab_m'][1]:.3f} "
            f"| {row['bias_mm']:.2f} | {row['taken_off_mm']:.2f} | {row['exact_inputs_mm']:.2f} |")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--model", required=True, help="model directory (a geometric model)")
    parser.add_argument("--quick", action="store_true", help="one small corner")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    model = load_model(args.model)
    print(f"Correction diagnosis, true A_fp {TRUE_FOOTPRINT_M2} m^2, seed {args.seed}: {platform.machine()}, "
          f"Python {platform.python_version()}, {date.today()}\n")
    print(HEADER)
    start = time.perf_counter()
    for index, (label, scene, edges) in enumerate(diagnosis_cases(args.quick)):
        rows = diagnose(label, scene, edges, model, seed=args.seed * 1000 + index)
        for row in rows:
            print(format_row(row), flush=True)
        if not rows:
            print(f"| {label} | the correction left the edges as measured |" + " |" * 7, flush=True)
    print(f"\nWall time: {time.perf_counter() - start:.0f} s")


if __name__ == "__main__":
    main()
