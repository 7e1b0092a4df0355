"""Every pixel at its noise limit: the fused baseline against the raw one, and the per-pixel uncertainty's coverage.

Run: .venv/bin/python -m benchmarks.noise_limit --model DIR [--seed 0] [--quick]
Renders, at Table I noise, a 90-degree corner of albedo 0.7 with a strong receiver footprint (0.073 m^2), a weak
one (0.002 m^2) and almost none (0.0007 m^2, also at albedo 0.2), and a flat wall turned 20 degrees, each at 2 m
(and the strong corner and the wall at 1 and 3.5 m), and corrects each with default options twice: with the raw
baseline (``--baseline raw``: the pixels the model leaves alone keep the highest frequency's depth) and with the
default fused baseline. Per scan one markdown row: the MAE of the measured 31.25 MHz depth, of the raw-baseline
output and of the fused one on the pixels all three have, the same within 20 cm of a corner's edge, the share of
pixels per estimate (measured, fused, corrected), the fused pixels' MAE over what their Cramer-Rao bound gives
(sqrt(2 / pi) sigma for Gaussian noise), and the share of pixels whose error lies within their 1-sigma uncertainty
(68 % for a calibrated Gaussian sigma), over all pixels, the fused ones and the corrected ones.
Then, where the model's card has an uncertainty model and its dataset is still at the card's path, the share of
the dataset's test rows (simulated, never seen in training) whose corrected error lies within the card's sigma,
per band of true range, beside the share within the measured depth's sd (the noise model alone).
``--quick`` runs the strong corner and the wall at 2 m only, small (for a test).
"""

from __future__ import annotations

import argparse
import platform
import time
from dataclasses import dataclass
from datetime import date
from pathlib import Path

import numpy as np

from benchmarks.envelope import framed_corner, render_with_footprint
from benchmarks.scenes import edge_line, edge_line_region, mae_mm
from mpi_lidar.config import SensorConfig
from mpi_lidar.correction import INVALID_FLAGS, CorrectionOptions, correct_scan
from mpi_lidar.correction.options import Estimate
from mpi_lidar.learning.error_model import coverage, error_terms
from mpi_lidar.learning.model import CorrectionModel, load_model
from mpi_lidar.learning.train import training_geometry
from mpi_lidar.physics.noise import depth_noise_m, fused_depths
from mpi_lidar.scans.scan import Scan
from mpi_lidar.simulation import dataset
from mpi_lidar.simulation.scenes import Scene, flat_wall

HEADER = ("| scan | raw MAE [mm] | raw baseline [mm] | fused baseline [mm] | change | edge raw baseline [mm] "
          "| edge fused baseline [mm] | measured / fused / corrected [%] | fused MAE / CRB | within 1 sigma: all "
          "/ fused / corrected [%] |\n|---|---|---|---|---|---|---|---|---|---|")
GAUSSIAN_MAE_PER_SIGMA = float(np.sqrt(2 / np.pi))
HELD_OUT_HEADER = ("| true range [m] | test rows | within the card's sigma [%] | within the measured sd [%] |\n"
                   "|---|---|---|---|")
HELD_OUT_BANDS_M = ((0.5, 1.0), (1.0, 2.0), (2.0, 4.0), (4.0, 8.0), (8.0, 12.0))


@dataclass(frozen=True)
class Case:
    """A scan of the run: label, scene, its corner's edge distance [m] (None: a wall) and true footprint [m^2]."""

    label: str
    scene: Scene
    edge_m: float | None
    footprint_m2: float


def cases(quick: bool) -> list[Case]:
    if quick:
        return [Case("corner at 2 m, 0.073 m^2", framed_corner(2.0, height=48, width=64), 2.0, 0.073),
                Case("wall at 2 m", flat_wall(20.0, 2.0, 0.7, height=48, width=64), None, 0.0)]
    runs = [Case(f"corner at {d:g} m, 0.073 m^2", framed_corner(d), d, 0.073) for d in (1.0, 2.0, 3.5)]
    runs += [Case("corner at 2 m, 0.002 m^2", framed_corner(2.0), 2.0, 0.002),
             Case("corner at 2 m, 0.0007 m^2", framed_corner(2.0), 2.0, 0.0007),
             Case("corner at 2 m, 0.0007 m^2, albedo 0.2", framed_corner(2.0, albedo=0.2), 2.0, 0.0007)]
    runs += [Case(f"wall at {d:g} m", flat_wall(20.0, d, 0.7), None, 0.0) for d in (1.0, 2.0, 3.5)]
    return runs


def rendered(case: Case, seed: int) -> Scan:
    return render_with_footprint(case.scene, case.footprint_m2, seed)


def measure(case: Case, scan: Scan, model: CorrectionModel) -> dict[str, float]:
    """The figures of one row (see the module's docstring)."""
    raw_run = correct_scan(scan, model, CorrectionOptions(baseline="raw"))
    fused_run = correct_scan(scan, model, CorrectionOptions())
    assert fused_run.measured_depth is not None and fused_run.estimate is not None
    assert fused_run.uncertainty_m is not None and scan.reference_depth is not None
    reference = scan.reference_depth
    usable = (np.isfinite(reference) & np.isfinite(fused_run.depth) & np.isfinite(raw_run.depth)
              & ~np.isin(fused_run.flags, [int(f) for f in INVALID_FLAGS]))
    edge = usable & (edge_line_region(scan, edge_line(case.edge_m)) if case.edge_m is not None else False)
    error = np.abs(fused_run.depth.astype(np.float64) - reference)
    sigma = fused_run.uncertainty_m.astype(np.float64)
    row = {"raw": mae_mm(fused_run.measured_depth, reference, usable),
           "raw_baseline": mae_mm(raw_run.depth, reference, usable),
           "fused_baseline": mae_mm(fused_run.depth, reference, usable),
           "edge_raw_baseline": mae_mm(raw_run.depth, reference, edge) if edge.any() else float("nan"),
           "edge_fused_baseline": mae_mm(fused_run.depth, reference, edge) if edge.any() else float("nan")}
    for estimate in Estimate:
        if estimate != Estimate.NONE:
            row[f"share_{estimate.name.lower()}"] = float((fused_run.estimate[usable] == estimate).mean())
    fused = usable & (fused_run.estimate == Estimate.FUSED)
    row["fused_over_crb"] = (float(error[fused].mean() / (GAUSSIAN_MAE_PER_SIGMA * cramer_rao_sd_m(scan)[fused].mean()))
                             if fused.any() else float("nan"))
    for name, where in (("all", usable & np.isfinite(sigma)), ("fused", fused),
                        ("corrected", usable & (fused_run.estimate == Estimate.CORRECTED))):
        row[f"covered_{name}"] = float((error[where] <= sigma[where]).mean()) if where.any() else float("nan")
    return row


def cramer_rao_sd_m(scan: Scan) -> np.ndarray:
    """The Cramer-Rao bound on a pixel's range sd (H, W) [m] under the moment model's noise at its amplitudes:
    (sum_f sigma_f^-2)^-1/2, the sd of the frequencies' inverse-variance mean."""
    f = len(scan.frequencies_hz)
    amplitude = np.asarray(scan.amplitude, dtype=np.float64).reshape(f, -1).T
    sigma = depth_noise_m(SensorConfig(), tuple(scan.frequencies_hz), np.maximum(amplitude, 1e-12))
    return ((sigma**-2.0).sum(1) ** -0.5).reshape(scan.shape)


def held_out_rows(model: CorrectionModel) -> list[str]:
    """Markdown rows of the corrected depths' coverage on the test split of the model's dataset, per band of true
    range and over all; none where the card has no uncertainty model or its dataset is not at the card's path."""
    uncertainty, path = model.card.uncertainty_model, Path(model.card.dataset.path)
    if uncertainty is None or not path.is_dir() or not dataset.is_complete(path):
        return []
    test = dataset.read_subsample(path, "test")
    config = test.info.config
    depth = model.predict_depth(test.features, training_geometry(model.spec, test))
    terms = error_terms(test.features, depth, test.target, config.frequencies_hz, config.sensor,
                        config.simulator.noise_scale)
    fused = fused_depths(test.features, config.frequencies_hz, config.sensor,
                         noise_scale=config.simulator.noise_scale)
    within_measured = np.abs(terms[:, 2]) <= fused.top_sigma_m * np.where(fused.consistent, 1.0, fused.birge_ratio)
    rows = []
    for label, band in [(f"{low:g}-{high:g}", (test.target >= low) & (test.target < high))
                        for low, high in HELD_OUT_BANDS_M] + [("all", np.ones(test.target.size, dtype=bool))]:
        if band.any():
            rows.append(f"| {label} | {int(band.sum()):,} | {100 * coverage(uncertainty, terms[band]):.1f} "
                        f"| {100 * within_measured[band].mean():.1f} |")
    return rows


def format_row(label: str, row: dict[str, float]) -> str:
    change = 100 * (row["fused_baseline"] / row["raw_baseline"] - 1)
    shares = " / ".join(f"{100 * row[f'share_{name}']:.0f}" for name in ("measured", "fused", "corrected"))
    covered = " / ".join(_cell(100 * row[f"covered_{name}"], ".0f") for name in ("all", "fused", "corrected"))
    return (f"| {label} | {row['raw']:.3f} | {row['raw_baseline']:.3f} | {row['fused_baseline']:.3f} "
            f"| {change:+.0f} % | {_cell(row['edge_raw_baseline'])} | {_cell(row['edge_fused_baseline'])} "
            f"| {shares} | {_cell(row['fused_over_crb'], '.3f')} | {covered} |")


def _cell(value: float, spec: str = ".3f") -> str:
    return "" if not np.isfinite(value) else format(value, spec)


def run(model_path: str, quick: bool = False, seed: int = 0) -> list[tuple[str, dict[str, float]]]:
    model = load_model(model_path)
    return [(case.label, measure(case, rendered(case, seed), model)) for case in cases(quick)]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--model", required=True)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--quick", action="store_true")
    args = parser.parse_args()
    model = load_model(args.model)
    started = time.perf_counter()
    print(f"model {args.model}: {model.spec.feature_set} inputs{', geometric' if model.geometric else ''}; "
          f"default options against --baseline raw; Table I noise, seed {args.seed}\n")
    print(HEADER)
    for case in cases(args.quick):
        print(format_row(case.label, measure(case, rendered(case, args.seed), model)), flush=True)
    uncertainty = model.card.uncertainty_model
    if uncertainty is not None:
        print(f"\nuncertainty model of the card: fused sd x {uncertainty.noise_factor:.3f} (+) "
              f"{1e3 * uncertainty.model_sd_m:.2f} mm x (|correction| / {1e3 * uncertainty.reference_correction_m:g} "
              f"mm)^{uncertainty.correction_exponent:.2f};\n{100 * uncertainty.validation_coverage:.1f} % of its "
              f"{uncertainty.validation_rows:,} validation rows within it")
    held_out = held_out_rows(model)
    if held_out:
        print(f"\nheld-out rows: the test split of {model.card.dataset.path}\n\n{HELD_OUT_HEADER}")
        print("\n".join(held_out))
    print(f"\n{platform.system()}, {platform.machine()}, Python {platform.python_version()}, {date.today()}, "
          f"{time.perf_counter() - started:.0f} s wall")


if __name__ == "__main__":
    main()
