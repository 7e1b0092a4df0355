"""A model for every range against the Bayes limit, band by band of the true range (0.5-12 m).

Run: .venv/bin/python -m benchmarks.range_bands [--rows 2000] [--train-rows 200000] [--seed 0] [--pool 1000] [--quick]

Draws a training set and a test set from the default prior with d_AS log-uniform over 0.5-12 m (as many rows
per octave of range), measured by the moment-matched sensor at Table I noise. Depths past a frequency's
unambiguous range (4.8 m at 31.25 MHz) are measured wrapped; both sets are unwrapped as a dataset's rows are
(:func:`mpi_lidar.simulation.dataset.simulate_rows`: the noise-weighted search over wrap counts of
:mod:`mpi_lidar.physics.unwrap`), and the table counts the test rows whose wrap counts it got wrong. The Bayes
limit takes the same rows (its likelihood does not depend on the wrap counts) with its proposal centred by the
true wrap count (:func:`truth_unwrapped`). XGBoost (the training's default parameters and objective, early-stopped
on every tenth training row) learns the residual target on three sets of inputs, none geometric (the Bayes
limit sees depth and amplitude only, so the models see what it sees): the ``range_free`` feature set; the same
plus the log albedo estimate ln(A d^2) of the highest frequency, the ``physical`` feature set (the default); and
``engineered``. Prints per band of true d_AS:
rows, rows unwrapped wrong, raw 31.25 MHz MAE, Bayes-limit MAE (posterior median, pool ``--pool``) +- its
standard error, its median effective sample size, each model's MAE and model / limit +- se. ``--quick``: a few
hundred rows, for a test (about 10 s on two idle cores).
"""

from __future__ import annotations

import argparse
import platform
import time
from datetime import date

import numpy as np
from numpy.typing import NDArray

from mpi_lidar.config import Config
from mpi_lidar.learning.features import FeatureSpec, weighted_depth
from mpi_lidar.learning.limits import posterior_estimates
from mpi_lidar.learning.model import depth_from_features
from mpi_lidar.learning.range_bands import RANGE_BANDS_M, BandErrors, range_band_errors
from mpi_lidar.learning.train import DEFAULT_PARAMS, DEFAULT_ROUNDS, train_arrays
from mpi_lidar.physics.demod import unambiguous_range
from mpi_lidar.simulation.dataset import seeded_rng
from mpi_lidar.workflows.bench import Sample, simulate

RANGE_M = (0.5, 12.0)
MODELS = ("range_free", "physical", "engineered")
STREAM = 2**21  # seed streams apart from those of datasets and other benchmarks on the same seed
QUICK = {"rows": 300, "train_rows": 20_000, "pool": 300}
THREADS = 2

HEADER = ("| true d_AS [m] | rows | unwrapped wrong | raw MAE [mm] | Bayes limit MAE [mm] | median ESS "
          + "".join(f"| {name} MAE [mm] | {name} / limit " for name in MODELS) + "|\n"
          + "|---" * (6 + 2 * len(MODELS)) + "|")


def range_config() -> Config:
    """The default configuration with d_AS log-uniform over :data:`RANGE_M`; every other field its default."""
    return Config().replace(prior={"d_as_m": RANGE_M, "d_as_distribution": "log_uniform"})


def truth_unwrapped(sample: Sample, config: Config) -> Sample:
    """``sample`` with each depth moved by whole unambiguous ranges c / 2f to within half of one of the truth.

    The wrap counts only a simulation knows: the Bayes limit's proposal is centred with them, as no other count
    carries posterior mass within 0.5-12 m (:mod:`mpi_lidar.learning.limits`).
    """
    f = len(config.frequencies_hz)
    ambiguity = unambiguous_range(config.frequencies_hz, config.sensor.speed_of_light_m_per_s)[None, :]
    depth = sample.raw[:, :f].astype(np.float64)
    depth = depth + np.round((sample.target[:, None] - depth) / ambiguity) * ambiguity
    return Sample(np.hstack([depth, sample.raw[:, f:].astype(np.float64)]), sample.target, sample.theta)


def model_inputs(raw: NDArray, model: str, config: Config) -> tuple[FeatureSpec, NDArray[np.float32]]:
    """The feature spec of ``model`` (a feature set of :data:`MODELS`) and its inputs for the rows ``raw``."""
    spec = FeatureSpec(config.frequencies_hz, model, "residual")
    return spec, spec.transform(raw)


def model_depth(train: Sample, test: Sample, model: str) -> tuple[NDArray[np.float64], int]:
    """The test rows' depth [m] by XGBoost trained on ``train`` with the inputs of ``model`` and the residual
    target, and the number of trees it kept."""
    config = range_config()
    spec, x = model_inputs(train.raw, model, config)
    result = train_arrays(x, spec.target(train.raw, train.target), DEFAULT_PARAMS, DEFAULT_ROUNDS, nthread=THREADS)
    return depth_from_features(result.booster, spec, test.raw, model_inputs(test.raw, model, config)[1]), \
        result.best_iteration + 1


def _mm(value: float, se: float | None = None) -> str:
    if not np.isfinite(value):
        return "-"
    return f"{1e3 * value:.3f}" + (f" ± {1e3 * se:.3f}" if se is not None and np.isfinite(se) else "")


def _ratio(band: BandErrors) -> str:
    return f"{band.ratio:.3f} ± {band.ratio_se:.3f}" if np.isfinite(band.ratio) else "-"


def format_row(per_set: list[BandErrors], wrong: int, ess: float) -> str:
    """One markdown row: the band's rows, wrongly unwrapped rows, raw and limit MAE, median effective sample
    size, then each model's MAE and ratio to the limit."""
    first = per_set[0]
    low, high = first.band_m
    cells = [f"{low:g}-{high:g}", f"{first.rows:,}", f"{wrong:,}", _mm(first.raw_mae_m),
             _mm(first.limit_mae_m, first.limit_se_m), f"{ess:.0f}" if np.isfinite(ess) else "-"]
    for band in per_set:
        cells += [_mm(band.model_mae_m), _ratio(band)]
    return "| " + " | ".join(cells) + " |"


def wrongly_unwrapped(test: Sample, config: Config) -> NDArray[np.bool_]:
    """Rows (n,) whose unwrapped depths lie half an unambiguous range or more from the truth at some frequency."""
    f = len(config.frequencies_hz)
    ambiguity = unambiguous_range(config.frequencies_hz, config.sensor.speed_of_light_m_per_s)[None, :]
    return np.any(np.abs(test.raw[:, :f] - test.target[:, None]) >= ambiguity / 2, axis=1)


def band_rows(test: Sample, posterior_median: NDArray, ess: NDArray, depths: dict[str, NDArray]) -> list[str]:
    """The table's rows: one per band of :data:`RANGE_BANDS_M`, then all rows together."""
    config = range_config()
    truth = test.target
    raw_top = test.raw[:, len(config.frequencies_hz) - 1]
    wrong = wrongly_unwrapped(test, config)
    rows = []
    for bands in (RANGE_BANDS_M, (RANGE_M,)):
        per_set = [range_band_errors(truth, raw_top, posterior_median, depths[name], bands) for name in MODELS]
        for index, (low, high) in enumerate(bands):
            inside = (truth >= low) & ((truth <= high) if index == len(bands) - 1 else (truth < high))
            median_ess = float(np.median(ess[inside])) if inside.any() else float("nan")
            rows.append(format_row([found[index] for found in per_set], int(wrong[inside].sum()), median_ess))
    return rows


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--rows", type=int, default=2_000, help="Test rows (Bayes limit and models).")
    parser.add_argument("--train-rows", type=int, default=200_000, help="Training rows of each model.")
    parser.add_argument("--pool", type=int, default=1_000, help="Particles per row of the Bayes limit.")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--quick", action="store_true", help="A few hundred rows, for a test (about 10 s).")
    args = parser.parse_args()
    if args.quick:
        args.rows, args.train_rows, args.pool = QUICK["rows"], QUICK["train_rows"], QUICK["pool"]
    started = time.perf_counter()
    config = range_config()
    stream = STREAM + 100 * args.seed
    train = simulate(config, args.train_rows, stream)
    test = simulate(config, args.rows, stream + 1)
    centre = weighted_depth(truth_unwrapped(test, config).raw, config.frequencies_hz)
    posterior = posterior_estimates(test.raw, config, seeded_rng(config.dataset.seed, stream + 2), pool=args.pool,
                                    range_m=centre)
    limit_s = time.perf_counter() - started
    depths, trees = {}, {}
    for name in MODELS:
        depths[name], trees[name] = model_depth(train, test, name)
    print(f"d_AS log-uniform over {RANGE_M[0]:g}-{RANGE_M[1]:g} m, the default prior otherwise; Table I noise; "
          f"{args.train_rows:,} training rows, {args.rows:,} test rows, seed {args.seed}; Bayes limit with pool "
          f"{args.pool:,}; XGBoost with the default parameters, residual target, no geometric inputs "
          f"({', '.join(f'{name}: {trees[name]} trees' for name in MODELS)}); depths unwrapped as a dataset's\n")
    print(HEADER)
    for row in band_rows(test, posterior.median_m, posterior.ess, depths):
        print(row)
    print(f"\n{platform.system()}, {platform.machine()}, Python {platform.python_version()}, {date.today()}, "
          f"{time.perf_counter() - started:.0f} s wall ({limit_s:.0f} s simulation and Bayes limit)")


if __name__ == "__main__":
    main()
