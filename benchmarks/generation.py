"""Distributed generation figures: wall time, throughput and worker peak memory on a LocalCluster.

Run: .venv/bin/python -m benchmarks.generation [--workers 2] [--dir /tmp/mpi-lidar-bench]
Generates the paper preset (1,338,670 rows) and a tenth of it with the moment simulator, and a small
waveform dataset whose throughput is extrapolated to the paper preset. Stores are deleted afterwards.
"""

from __future__ import annotations

import argparse
import platform
import resource
import shutil
import tempfile
from datetime import date
from pathlib import Path

from mpi_lidar.config import PAPER_SAMPLES, preset
from mpi_lidar.workflows.cluster import dask_client
from mpi_lidar.workflows.generate import GenerationReport, generate


def peak_rss_mib() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


def run(client, root: Path, name: str, **overrides: object) -> GenerationReport:
    config = preset("paper").replace(**overrides)
    path = root / f"{name}.zarr"
    try:
        return generate(path, config, client)
    finally:
        shutil.rmtree(path, ignore_errors=True)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--dir", type=Path, default=None, help="where the temporary stores go")
    args = parser.parse_args()
    root = Path(tempfile.mkdtemp(prefix="mpi-lidar-bench-", dir=args.dir))
    print(f"Machine: {platform.node()} ({platform.machine()}, {platform.python_version()}), {date.today()}, "
          f"LocalCluster of {args.workers} worker processes x 1 thread\n")
    print("| run | rows | chunks | wall [s] | rows/s |\n|---|---|---|---|---|")
    try:
        with dask_client(workers=args.workers) as client:
            rows = {}
            for name, samples, overrides in [
                ("paper, moment", PAPER_SAMPLES, {}),
                ("paper / 10, moment", PAPER_SAMPLES // 10, {"dataset": {"samples": PAPER_SAMPLES // 10,
                                                                         "chunk_rows": 6_554}}),
                ("waveform", 8_000, {"dataset": {"samples": 8_000, "chunk_rows": 500},
                                     "simulator": {"fidelity": "waveform"}}),
            ]:
                report = run(client, root, name.split(",")[0].replace(" ", ""), **overrides)
                rows[name] = report
                print(f"| {name} | {samples:,} | {report.chunks_written} | {report.wall_s:.2f} | "
                      f"{report.rows_per_s:,.0f} |")
            peaks = client.run(peak_rss_mib)
        waveform_rate = rows["waveform"].rows_per_s
        print(f"\nWorker peak RSS: {', '.join(f'{v:.0f} MiB' for v in peaks.values())}")
        print(f"Waveform fidelity, paper preset extrapolated: {PAPER_SAMPLES / waveform_rate / 60:.0f} min "
              f"at {waveform_rate:,.0f} rows/s")
    finally:
        shutil.rmtree(root, ignore_errors=True)


if __name__ == "__main__":
    main()
