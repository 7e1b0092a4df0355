"""mpi-lidar bench: run time against error for every estimator."""

from __future__ import annotations

from pathlib import Path

import click

from mpi_lidar.cli._declared import bounded
from mpi_lidar.terminal import Display, print_table
from mpi_lidar.workflows.job_options import Seed


@click.command()
@click.option("--out", "out_dir", type=click.Path(path_type=Path), required=True, help="Report directory.")
@click.option("--rows", type=click.IntRange(min=100), help="Train rows (default 50,000; the test set is half).")
@click.option("--quick", is_flag=True, help="Tiny sizes (seconds), for a first look and for tests.")
@click.option("--seed", type=bounded(Seed), help="Seed of the simulated rows (default: the config's).")
def bench(out_dir: Path, rows: int | None, quick: bool, seed: int | None) -> None:
    """Run time against error: test MAE, training time and throughput of every estimator, Pareto fronts.

    \b
    Example:
      mpi-lidar bench --out runs/bench --quick
    """
    import dataclasses
    import os
    import platform

    from mpi_lidar.config import Config
    from mpi_lidar.workflows.bench import BenchPlan, run_bench, tradeoff_table, write_bench

    plan = BenchPlan.quick() if quick else BenchPlan()
    if rows is not None:
        plan = dataclasses.replace(plan, rows=rows, test_rows=max(10, rows // 2))
    config = Config() if seed is None else Config().replace(dataset={"seed": seed})
    with Display() as display, display.step("bench") as advance:
        result = run_bench(plan, config, on_step=advance)
    machine = f"Machine: {platform.machine()}, {os.cpu_count()} cores, Python {platform.python_version()}. "
    write_bench(result, out_dir, machine)
    table = tradeoff_table(result)
    print_table(table.headers, table.rows)
    click.echo(f"report written to {out_dir} ({result.wall_s:.0f} s)")
