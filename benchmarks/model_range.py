"""The correction model beyond its prior's d_AS range: how far past it batch correction may trust it.

Run: .venv/bin/python -m benchmarks.model_range --model DIR [--rows 40000] [--seed 0]
Simulates rows from the model's own prior and sensor (Table I noise) whose true d_AS lies in bins below,
inside and above the prior's range, gives them the geometric inputs a scan's geometry would give (geometric
models), and prints one markdown row per bin: the MAE of the 31.25 MHz depth and of the model, over all
rows and over the rows whose multipath bias is below 4 mm (the geometry gate's default threshold: where a
wrong correction harms most), and the share of rows batch correction's range rule lets the model correct
(:func:`mpi_lidar.correction.correct.in_model_range`, default options). Multipath only lengthens a path, so
a depth measured below the prior's range is truly that near; above it the measured depth may be a nearer
surface pushed out by multipath.
"""

from __future__ import annotations

import argparse
import platform
import time
from collections.abc import Iterator
from dataclasses import dataclass
from datetime import date

import numpy as np

from mpi_lidar.config import Config
from mpi_lidar.correction import CorrectionOptions, in_model_range
from mpi_lidar.learning.features import synthetic_geometry
from mpi_lidar.learning.model import CorrectionModel, load_model
from mpi_lidar.simulation.sampling import THETA_NAMES
from mpi_lidar.workflows.bench import simulate, top_depth

# Bins of the true d_AS as fractions of the prior's nearest (below) and farthest (above) d_AS.
BELOW = ((0.70, 0.80), (0.80, 0.85), (0.85, 0.90), (0.90, 0.95), (0.95, 1.00), (1.00, 1.07))
ABOVE = ((0.96, 1.00), (1.00, 1.02), (1.02, 1.05), (1.05, 1.10))
WEAK_BIAS_M = 0.004
STREAM = 2**20  # seed streams apart from those of datasets and benchmarks on the same seed

HEADER = ("| true d_AS [m] | rows | corrected by the range rule | raw MAE [mm] | model MAE [mm] "
          "| weak rows | weak raw MAE [mm] | weak model MAE [mm] | range rule MAE [mm] |\n"
          "|---|---|---|---|---|---|---|---|---|")


@dataclass(frozen=True)
class RangeBin:
    """MAEs [mm] of one bin of true d_AS [m]; "weak": the rows whose multipath bias is below 4 mm."""

    d_as_m: tuple[float, float]
    rows: int
    corrected_share: float
    raw_mm: float
    model_mm: float
    weak_rows: int
    weak_raw_mm: float
    weak_model_mm: float
    rule_mm: float


def bins_m(d_as_m: tuple[float, float]) -> list[tuple[float, float]]:
    """The bins of true d_AS [m] around a prior's range ``d_as_m`` [m]."""
    low, high = d_as_m
    return [(low * a, low * b) for a, b in BELOW] + [(high * a, high * b) for a, b in ABOVE]


def _mae_mm(error: np.ndarray) -> float:
    return float(1e3 * np.mean(np.abs(error))) if error.size else float("nan")


def measure_bin(model: CorrectionModel, d_as_m: tuple[float, float], rows: int, stream: int,
                options: CorrectionOptions) -> RangeBin:
    """One bin: ``rows`` rows of the model's prior with the true d_AS drawn in ``d_as_m`` [m]."""
    card = model.card
    config = Config().replace(prior=card.dataset.prior.model_dump(), simulator=card.dataset.simulator.model_dump())
    sample = simulate(config, rows, stream, d_as_m=d_as_m)
    geometry = None
    if model.geometric:
        errors = card.geometry_error_model.model_dump() if card.geometry_error_model else None
        geometry = synthetic_geometry(sample.theta, THETA_NAMES, config.dataset.seed + stream,
                                      np.arange(rows), errors)
    truth = sample.target
    measured = top_depth(config.frequencies_hz)(sample.raw)
    corrected = model.predict_depth(sample.raw, geometry)
    inside = in_model_range(measured, model, options)
    rule = np.where(inside, corrected, measured)
    weak = (measured - truth) < WEAK_BIAS_M
    return RangeBin(d_as_m, rows, float(inside.mean()), _mae_mm(measured - truth), _mae_mm(corrected - truth),
                    int(weak.sum()), _mae_mm((measured - truth)[weak]), _mae_mm((corrected - truth)[weak]),
                    _mae_mm(rule - truth))


def run(model: CorrectionModel, rows: int, seed: int = 0) -> Iterator[RangeBin]:
    """The bins of :func:`bins_m` around the model's prior, one at a time, under the default options."""
    options = CorrectionOptions()
    for index, span in enumerate(bins_m(model.card.dataset.prior.d_as_m)):
        yield measure_bin(model, span, rows, STREAM + 100 * seed + index, options)


def format_row(b: RangeBin) -> str:
    return (f"| {b.d_as_m[0]:.2f}-{b.d_as_m[1]:.2f} | {b.rows:,} | {100 * b.corrected_share:.0f} % "
            f"| {b.raw_mm:.3f} | {b.model_mm:.3f} | {b.weak_rows:,} | {b.weak_raw_mm:.3f} | {b.weak_model_mm:.3f} "
            f"| {b.rule_mm:.3f} |")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--model", required=True, help="Directory of a trained correction model.")
    parser.add_argument("--rows", type=int, default=40_000, help="Simulated rows per bin.")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    started = time.perf_counter()
    model = load_model(args.model)
    options = CorrectionOptions()
    low, high = model.card.dataset.prior.d_as_m
    print(f"Model {args.model} ({model.booster.num_boosted_rounds()} trees, geometric: {model.geometric}), "
          f"prior d_AS {low:g}-{high:g} m; range rule: measured depth in "
          f"[{low * (1 - options.near_range_fraction):.3g}, {high:g}] m (+-{options.range_tolerance_m:g} m)\n")
    print(HEADER, flush=True)
    for found in run(model, args.rows, args.seed):
        print(format_row(found), flush=True)
    print(f"\n{platform.machine()}, {platform.python_version()}, {date.today()}, "
          f"{time.perf_counter() - started:.0f} s wall")


if __name__ == "__main__":
    main()
