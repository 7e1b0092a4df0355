"""Closing the distance to the limit: XGBoost test MAE per feature set and target mode, per noise scale.

    .venv/bin/python -m benchmarks.tradeoff features [--train-rows N] [--test-rows N] [--noise 1,0.3,...]
    .venv/bin/python -m benchmarks.tradeoff limit [--train-rows N] [--test-rows N] [--noise 1,0.3,...]

Train and test rows are independent draws from the default prior (separate seed streams); XGBoost uses the
project's BASE_PARAMS and DEFAULT_PARAMS (``--objective reg:squarederror`` for the former objective) with
early stopping on every tenth train row. Prints one markdown table.
``limit`` compares the default model (engineered features, residual target, BASE_PARAMS and
DEFAULT_PARAMS, early-stopped) with the posterior median of :mod:`mpi_lidar.learning.limits` on the same test rows:
the paired difference of absolute errors has a much smaller standard error than either MAE.
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from mpi_lidar.config import Config
from mpi_lidar.learning.features import FEATURE_SETS, TARGET_MODES, FeatureSpec
from mpi_lidar.learning.model import booster_depth
from mpi_lidar.learning.train import DEFAULT_PARAMS, train_arrays
from mpi_lidar.workflows.bench import TEST_STREAM, TRAIN_STREAM, mae, reference_xgboost, simulate


def features(train_rows: int, test_rows: int, noise_scales: list[float], sets: list[str], modes: list[str],
             nthread: int, objective: str | None = None, early_stopping: int = 50) -> None:
    config = Config()
    print("| noise scale | feature set | target | trees | fit [s] | test MAE [mm] |")
    print("|---|---|---|---|---|---|")
    for noise in noise_scales:
        train = simulate(config, train_rows, TRAIN_STREAM, noise_scale=noise)
        test = simulate(config, test_rows, TEST_STREAM, noise_scale=noise)
        raw_mae = mae(test.raw[:, len(config.frequencies_hz) - 1], test.target)
        print(f"| {noise:g} | raw depth 31.25 MHz | | | | {1e3 * raw_mae:.3f} |", flush=True)
        for feature_set in sets:
            for mode in modes:
                spec = FeatureSpec(config.frequencies_hz, feature_set, mode)
                fitted = train_arrays(*train.inputs(spec),
                                      {**DEFAULT_PARAMS, **({"objective": objective} if objective else {})},
                                      4000, early_stopping_rounds=early_stopping, nthread=nthread)
                booster = fitted.booster
                err = mae(booster_depth(booster, spec, test.raw), test.target)
                print(f"| {noise:g} | {feature_set} | {mode} | {booster.num_boosted_rounds()} | {fitted.wall_s:.1f} "
                      f"| {1e3 * err:.3f} |", flush=True)


def limit(train_rows: int, test_rows: int, noise_scales: list[float], seed: int = 5) -> None:
    from mpi_lidar.learning.features import DEFAULT_FEATURE_SET, DEFAULT_TARGET_MODE
    from mpi_lidar.learning.limits import posterior_estimates

    config = Config()
    spec = FeatureSpec(config.frequencies_hz, DEFAULT_FEATURE_SET, DEFAULT_TARGET_MODE)
    print("| noise scale | test rows | raw 31.25 MHz [mm] | XGBoost [mm] | posterior median [mm] | XGBoost - posterior "
          "[mm] | ratio | median ESS |")
    print("|---|---|---|---|---|---|---|---|")
    for noise in noise_scales:
        train = simulate(config, train_rows, TRAIN_STREAM, noise_scale=noise)
        test = simulate(config, test_rows, TEST_STREAM + 7, noise_scale=noise)
        booster = reference_xgboost(spec, train).booster
        post = posterior_estimates(test.raw.astype(np.float64), config.replace(simulator={"noise_scale": noise}),
                                   np.random.default_rng(seed))
        ex = np.abs(booster_depth(booster, spec, test.raw) - test.target)
        eb = np.abs(post.median_m - test.target)
        er = np.abs(test.raw[:, len(config.frequencies_hz) - 1] - test.target)
        se = lambda v: 1e3 * v.std(ddof=1) / np.sqrt(v.size)  # noqa: E731
        print(f"| {noise:g} | {test_rows:,} | {1e3 * er.mean():.3f} | {1e3 * ex.mean():.3f} | {1e3 * eb.mean():.3f} "
              f"+- {se(eb):.3f} | {1e3 * (ex - eb).mean():.3f} +- {se(ex - eb):.3f} | {ex.mean() / eb.mean():.3f} "
              f"| {np.median(post.ess):.0f} |", flush=True)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest="command", required=True)
    p = sub.add_parser("features")
    p.add_argument("--train-rows", type=int, default=300_000)
    p.add_argument("--test-rows", type=int, default=100_000)
    p.add_argument("--noise", default="1")
    p.add_argument("--sets", default=",".join(FEATURE_SETS))
    p.add_argument("--modes", default=",".join(TARGET_MODES))
    p.add_argument("--nthread", type=int, default=1)
    p.add_argument("--objective", help="XGBoost objective (default: train.BASE_PARAMS', reg:absoluteerror)")
    p.add_argument("--early-stopping", type=int, default=50)
    q = sub.add_parser("limit")
    q.add_argument("--train-rows", type=int, default=200_000)
    q.add_argument("--test-rows", type=int, default=1_500)
    q.add_argument("--noise", default="1,0.3,0.1,0.01")
    args = parser.parse_args()
    started = time.perf_counter()
    if args.command == "limit":
        limit(args.train_rows, args.test_rows, [float(v) for v in args.noise.split(",")])
        print(f"\n{time.perf_counter() - started:.0f} s in all")
        return
    features(args.train_rows, args.test_rows, [float(v) for v in args.noise.split(",")], args.sets.split(","),
             args.modes.split(","), args.nthread, args.objective, args.early_stopping)
    print(f"\n{time.perf_counter() - started:.0f} s in all")


if __name__ == "__main__":
    main()
