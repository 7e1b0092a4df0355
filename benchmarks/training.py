"""Training and tuning figures on a stored dataset (the paper preset: ~1.07 M train rows).

Run: .venv/bin/python -m benchmarks.training --data PATH [--trials 30] [--tune-rows 100000] [--skip-tuning]
Final XGBoost training through xgboost.dask on a 2-worker LocalCluster (wall time, trees, test MAE), then
``--trials`` TPE trials on a fresh SQLite study with 2 parallel workers and with 1 worker.
"""

from __future__ import annotations

import argparse
import platform
import shutil
import tempfile
import time
from datetime import date
from pathlib import Path

from mpi_lidar.learning import tune
from mpi_lidar.learning.evaluate import error_metrics
from mpi_lidar.learning.features import DEFAULT_FEATURE_SET, DEFAULT_TARGET_MODE, FeatureSpec
from mpi_lidar.learning.model import load_model
from mpi_lidar.learning.train import train_and_save
from mpi_lidar.simulation import dataset
from mpi_lidar.workflows.cluster import dask_client


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", required=True)
    parser.add_argument("--trials", type=int, default=30)
    parser.add_argument("--tune-rows", type=int, default=tune.DEFAULT_TUNE_ROWS)
    parser.add_argument("--skip-tuning", action="store_true")
    args = parser.parse_args()
    info = dataset.dataset_info(args.data)
    spec = FeatureSpec(info.frequencies_hz, DEFAULT_FEATURE_SET, DEFAULT_TARGET_MODE)
    scratch = Path(tempfile.mkdtemp(prefix="mpi-lidar-bench-"))
    print(f"Machine: {platform.node()} ({platform.machine()}), {date.today()}; dataset {args.data} "
          f"({info.samples:,} rows)\n")
    try:
        with dask_client(workers=2) as client:
            _, result = train_and_save(client, args.data, scratch / "model", spec)
        test = dataset.read_subsample(args.data, split="test")
        mae = error_metrics(load_model(scratch / "model").predict_depth(test.features), test.target).mae_m
        print("| final training (2 workers) | rows | trees | wall [s] | test MAE [mm] |\n|---|---|---|---|---|")
        print(f"| xgboost.dask, default parameters | {result.fit_rows:,} | {result.best_iteration + 1} | "
              f"{result.wall_s:.1f} | {1e3 * mae:.3f} |\n")
        if args.skip_tuning:
            return
        print("| tuning | trials | wall [s] | trials/min | best validation MAE [mm] |\n|---|---|---|---|---|")
        settings = tune.TuneSettings(args.data, spec, tune_rows=args.tune_rows)
        for workers in (2, 1):
            storage = f"sqlite:///{scratch / f'optuna-{workers}.db'}"
            with dask_client(workers=workers) as client:
                started = time.perf_counter()
                report = tune.tune(client, storage, "bench", settings, args.trials)
                wall = time.perf_counter() - started
            print(f"| {workers} worker{'s' * (workers > 1)} | {report.trials_run} | {wall:.0f} | "
                  f"{60 * report.trials_run / wall:.2f} | {1e3 * report.best_value_m:.3f} |")
    finally:
        shutil.rmtree(scratch, ignore_errors=True)


if __name__ == "__main__":
    main()
