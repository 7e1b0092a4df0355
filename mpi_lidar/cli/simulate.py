"""mpi-lidar simulate: a labelled dataset store."""

from __future__ import annotations

from pathlib import Path

import click

from mpi_lidar.cli._common import SENSOR_SIMULATION_HELP, for_sensor
from mpi_lidar.cli._declared import bounded
from mpi_lidar.config import PRESETS, DatasetConfig, resolve_config
from mpi_lidar.terminal import Display, plural, print_table
from mpi_lidar.workflows.job_options import Workers


@click.command()
@click.option("--out", "out", required=True,
              help="Dataset store to write (.zarr): a path or a URL (s3://, gs://, az://).")
@click.option("--config", "config_file", type=click.Path(path_type=Path), help="TOML file overriding the preset.")
@click.option("--preset", "preset_name", type=click.Choice(sorted(PRESETS)), default="quick", show_default=True)
@click.option("--samples", type=bounded(DatasetConfig.model_fields["samples"]),
              help="Number of rows (overrides the preset and file).")
@click.option("--chunk-rows", type=bounded(DatasetConfig.model_fields["chunk_rows"]), help="Rows per chunk.")
@click.option("--seed", type=bounded(DatasetConfig.model_fields["seed"]), help="Seed of the sampling plan.")
@click.option("--fidelity", type=click.Choice(["moment", "waveform"]), help="Simulator fidelity.")
@click.option("--sensor", "sensor", type=click.Path(path_type=Path), default=None, help=SENSOR_SIMULATION_HELP)
@click.option("--workers", type=bounded(Workers), default=2, show_default=True,
              help="Dask worker processes of a local cluster; 0 runs in this process.")
@click.option("--scheduler", help="Address of a running Dask scheduler (tcp://host:8786) instead of a local cluster.")
def simulate(
    out: str, config_file: Path | None, preset_name: str, samples: int | None, chunk_rows: int | None,
    seed: int | None, fidelity: str | None, sensor: Path | None, workers: int, scheduler: str | None,
) -> None:
    """Simulate a labelled dataset and print its raw-error summary.

    \b
    Example:
      mpi-lidar simulate --out runs/d.zarr --samples 20000 --workers 2

    Re-running on a complete store of the same configuration only prints the summary; an interrupted
    store resumes where it stopped.
    """
    from mpi_lidar.simulation import dataset

    config = for_sensor(resolve_config(config_file, preset_name, samples=samples, chunk_rows=chunk_rows, seed=seed,
                                       fidelity=fidelity), sensor)

    from mpi_lidar.workflows.executor import InProcess, dask_executor
    from mpi_lidar.workflows.generate import generate

    plan = dataset.SamplingPlan.from_config(config)
    todo = len(dataset.incomplete_chunks(dataset.create_store(out, config)))
    with Display() as display, display.step("simulating chunks", todo) as advance:
        with InProcess() if not todo or workers == 0 else dask_executor(scheduler, workers) as executor:
            report = generate(out, config, executor, on_chunk=lambda _i: advance())
    summary = dataset.summarize(out)
    click.echo(f"dataset {summary.path}: {plural(summary.samples, 'row')} ({summary.train:,} train, "
               f"{summary.test:,} test), config {summary.config_sha256[:12]}")
    print_table(("frequency", "raw MAE [mm]", "raw RMSE [mm]", "noise-only MAE [mm]"),
                [(f"{f / 1e6:g} MHz", f"{1e3 * mae:.3f}", f"{1e3 * rmse:.3f}", f"{1e3 * noise:.3f}")
                 for f, mae, rmse, noise in zip(summary.frequencies_hz, summary.mae_m, summary.rmse_m,
                                                summary.noise_only_mae_m, strict=True)])
    click.echo(f"noise-only: the same scenes without the A -> B -> A path, first {summary.noise_only_rows:,} rows")
    click.echo(f"{report.chunks_written} of {plural(plan.chunks, 'chunk')} simulated in {report.wall_s:.1f} s "
               f"({report.rows_per_s:,.0f} rows/s, {config.simulator.fidelity} fidelity)")
