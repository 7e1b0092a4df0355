"""Cluster figures: a process cluster next to one process, tuning trials per minute, batch correction scans per minute.

Run: .venv/bin/python -m benchmarks.cluster [--samples 40000] [--trials 8] [--scans 60] [--workers 1,2,4]
     [--postgres postgresql://postgres@127.0.0.1:5432/postgres]

1. Generation and batch correction in this process (no Dask), then on ``dask scheduler`` + two
   ``dask worker`` processes (one thread each) started on 127.0.0.1, as users start them.
2. Tuning: ``--trials`` trials of one PostgreSQL study (a fresh database, dropped afterwards) with a
   LocalCluster of 1, 2 and 4 worker processes (one trial process each).
3. Batch correction of ``--scans`` small scans (32 x 48 pixels, four frequencies) in one batch.

Wall times exclude starting clusters and the workers' first imports (a small warm-up run). Prints
Markdown tables for docs/results/cluster.md.
"""

from __future__ import annotations

import argparse
import logging
import os
import platform
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import time
import uuid
from collections.abc import Iterator
from contextlib import contextmanager
from datetime import date
from pathlib import Path

from distributed import Client, LocalCluster

from mpi_lidar.config import Config
from mpi_lidar.correction import CorrectionOptions
from mpi_lidar.learning import tune
from mpi_lidar.learning.features import FeatureSpec
from mpi_lidar.learning.train import train_and_save
from mpi_lidar.scans.store import write_scan
from mpi_lidar.workflows.correct_archive import correct_archive
from mpi_lidar.workflows.generate import generate

BIN = Path(sys.executable).parent


@contextmanager
def process_cluster(workers: int = 2) -> Iterator[str]:
    """``dask scheduler`` and ``dask worker`` processes on 127.0.0.1; yields the scheduler address."""
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        port = probe.getsockname()[1]
    env = {**os.environ, "DASK_LOGGING__DISTRIBUTED": "error"}
    quiet = {"stdout": subprocess.DEVNULL, "stderr": subprocess.DEVNULL, "env": env, "start_new_session": True}
    address = f"tcp://127.0.0.1:{port}"
    processes = [subprocess.Popen([str(BIN / "dask"), "scheduler", "--host", "127.0.0.1", "--port", str(port),
                                   "--no-dashboard"], **quiet)]
    try:
        time.sleep(2)
        processes += [subprocess.Popen([str(BIN / "dask"), "worker", address, "--nworkers", "1", "--nthreads", "1",
                                        "--no-dashboard", "--host", "127.0.0.1"], **quiet) for _ in range(workers)]
        with Client(address, timeout=120) as client:
            client.wait_for_workers(workers, timeout=120)
        yield address
    finally:
        for process in processes:
            os.killpg(process.pid, signal.SIGKILL)
            process.wait()


@contextmanager
def postgres_database(admin_url: str) -> Iterator[str]:
    import psycopg

    name = f"mpi_lidar_bench_{uuid.uuid4().hex[:8]}"
    with psycopg.connect(admin_url, autocommit=True) as admin:
        admin.execute(f'CREATE DATABASE "{name}"')
    try:
        yield admin_url.rsplit("/", 1)[0] + f"/{name}"
    finally:
        with psycopg.connect(admin_url, autocommit=True) as admin:
            admin.execute(f'DROP DATABASE IF EXISTS "{name}" WITH (FORCE)')


def timed(run) -> float:
    started = time.perf_counter()
    run()
    return time.perf_counter() - started


def small_scans(root: Path, count: int) -> Path:
    from tests.scan_factory import two_path_scan

    for index in range(count):
        write_scan(two_path_scan(f"s{index:04d}", 32, 48, seed=index), root / f"s{index:04d}.scan.zarr")
    return root


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--samples", type=int, default=40_000)
    parser.add_argument("--trials", type=int, default=8)
    parser.add_argument("--scans", type=int, default=60)
    parser.add_argument("--workers", default="1,2,4")
    parser.add_argument("--postgres", default="postgresql://postgres@127.0.0.1:5432/postgres")
    args = parser.parse_args()
    work = Path(tempfile.mkdtemp(prefix="mpi-lidar-bench-cluster-"))
    config = Config().replace(dataset={"samples": args.samples, "chunk_rows": args.samples // 8, "seed": 1})
    options = CorrectionOptions(gate="all")
    print(f"Machine: {platform.node()} ({platform.machine()}, {os.cpu_count()} cores), Python "
          f"{platform.python_version()}, {date.today()}; work directory {work}\n")
    try:
        data = work / "dataset.zarr"
        local_gen = timed(lambda: generate(work / "local.zarr", config))
        archive = small_scans(work / "archive", args.scans)
        with process_cluster(2) as address, Client(address) as client:
            warm = config.replace(dataset={"samples": 400, "chunk_rows": 100})
            generate(work / "warm.zarr", warm, client)  # imports and sensor caches in every worker
            cluster_gen = timed(lambda: generate(data, config, client))
            model, _ = train_and_save(client, data, work / "model", FeatureSpec(config.frequencies_hz),
                                      {"max_depth": 6, "learning_rate": 0.3}, num_boost_round=100)
            cluster_correct = timed(lambda: correct_archive([str(archive)], model, work / "out-cluster",
                                                            options, client))
        local_correct = timed(lambda: correct_archive([str(archive)], model, work / "out-local", options))
        done = sum(1 for p in (work / "out-cluster").iterdir() if (p / "corrected.zarr").is_dir())
        print("| step | one process [s] | dask scheduler + 2 worker processes [s] |")
        print("|---|---|---|")
        print(f"| generate {args.samples:,} rows (8 chunks) | {local_gen:.1f} | {cluster_gen:.1f} |")
        print(f"| correct {args.scans} scans of 32 x 48 px ({done} written) | {local_correct:.1f} | "
              f"{cluster_correct:.1f} |")
        print(f"\nscans per minute: {60 * args.scans / local_correct:.0f} in one process, "
              f"{60 * args.scans / cluster_correct:.0f} on the process cluster\n")

        settings = tune.TuneSettings(str(data), FeatureSpec(config.frequencies_hz), tune_rows=5_000,
                                     num_boost_round=200, early_stopping_rounds=20)
        print("| trial processes | trials | complete + pruned | wall [s] | trials/min |")
        print("|---|---|---|---|---|")
        for workers in (int(w) for w in args.workers.split(",")):
            with (postgres_database(args.postgres) as url,
                  LocalCluster(n_workers=workers, threads_per_worker=1, processes=True, dashboard_address=":0",
                               silence_logs=logging.ERROR) as cluster, Client(cluster) as client):
                tune.open_study(url, "bench", settings)  # created once, before the trials start
                report = tune.tune(client, url, "bench", settings, trials=args.trials)
            print(f"| {workers} | {report.trials_run} | {report.complete + report.pruned} | {report.wall_s:.1f} | "
                  f"{60 * report.trials_run / report.wall_s:.1f} |")
    finally:
        shutil.rmtree(work, ignore_errors=True)


if __name__ == "__main__":
    main()
