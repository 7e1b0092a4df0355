"""mpi-lidar pipeline: the main job, from simulation to the demo scenes' correction, in one run directory."""

from __future__ import annotations

from pathlib import Path

import click

from mpi_lidar.cli._common import SENSOR_SIMULATION_HELP, cluster_options, for_sensor
from mpi_lidar.cli._declared import bounded
from mpi_lidar.config import PRESETS, resolve_config
from mpi_lidar.terminal import Display
from mpi_lidar.workflows.job_options import Trials, TuneRows


@click.command()
@click.option("--out", "out_dir", type=click.Path(path_type=Path), default=None,
              help="Run directory: dataset.zarr, optuna.db, model/, report/ (default: runs/<preset>).")
@click.option("--config", "config_file", type=click.Path(path_type=Path), help="TOML file overriding the preset.")
@click.option("--preset", "preset_name", type=click.Choice(sorted(PRESETS)), default="quick", show_default=True)
@click.option("--trials", type=bounded(Trials), default=6, show_default=True, help="Tuning budget.")
@click.option("--tune-rows", type=bounded(TuneRows), default=20_000, show_default=True)
@click.option("--sensor", "sensor", type=click.Path(path_type=Path), default=None, help=SENSOR_SIMULATION_HELP)
@cluster_options
def pipeline(out_dir: Path, config_file: Path | None, preset_name: str, trials: int, tune_rows: int,
             sensor: Path | None, workers: int, scheduler: str | None) -> None:
    """The main job: simulate, tune, train and evaluate into one run directory (resumable).

    \b
    Example:
      mpi-lidar pipeline --preset quick --out runs/quick
    """
    from mpi_lidar.workflows.cluster import dask_client
    from mpi_lidar.workflows.pipeline import ClusterSteps, run_pipeline

    config = for_sensor(resolve_config(config_file, preset_name), sensor)
    out_dir = out_dir or Path("runs") / preset_name
    with Display() as display, dask_client(scheduler, workers) as client:
        result = run_pipeline(ClusterSteps(client, display.step), out_dir, config, trials, tune_rows,
                              echo=display.echo)
    metrics = result.evaluation.metrics
    raw, corrected = metrics[result.evaluation.raw_label], metrics["corrected (XGBoost)"]
    click.echo(f"test split: {result.evaluation.raw_label} MAE {1e3 * raw.mae_m:.3f} mm -> corrected "
               f"{1e3 * corrected.mae_m:.3f} mm; report in {result.report_dir}/report.html")
    for outcome in result.scans:
        masked = outcome.metrics.get("masked region", {})
        change = (f"masked MAE {1e3 * masked['raw_mae_m']:.3f} -> {1e3 * masked['corrected_mae_m']:.3f} mm"
                  if masked else outcome.reason)
        click.echo(f"scene {outcome.name}: {outcome.status}, {change}; {outcome.output}/report.html")
