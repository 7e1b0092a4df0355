"""Command line: ``mpi-lidar simulate ...``. Every user error is one line on stderr and exit code 2."""

from __future__ import annotations

import sys
from pathlib import Path

import click
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn

from mpi_lidar.config import PRESETS, Config, load_config, preset, validate_overrides
from mpi_lidar.errors import MpiLidarError

EXIT_USER_ERROR = 2


def build_config(
    config_file: Path | None, preset_name: str, overrides: dict[str, dict[str, object]]
) -> Config:
    """Preset, then the TOML file's tables, then command-line overrides; validated at each step."""
    config = preset(preset_name)
    if config_file is not None:
        config = load_config(config_file, base=config)
    overrides = {section: values for section, values in overrides.items() if values}
    if overrides:
        config = validate_overrides(overrides, config, source="command line")
    return config


@click.group(context_settings={"help_option_names": ["-h", "--help"]})
@click.version_option(package_name="mpi-lidar")
def cli() -> None:
    """Multipath-interference suppression for AMCW coaxial scanning LiDAR."""


@cli.command()
@click.option("--out", "out", type=click.Path(path_type=Path), required=True, help="Dataset store to write (.zarr).")
@click.option("--config", "config_file", type=click.Path(path_type=Path), help="TOML file overriding the preset.")
@click.option("--preset", "preset_name", type=click.Choice(sorted(PRESETS)), default="quick", show_default=True)
@click.option("--samples", type=int, help="Number of rows (overrides the preset and file).")
@click.option("--chunk-rows", type=int, help="Rows per chunk.")
@click.option("--seed", type=int, help="Seed of the sampling plan.")
@click.option("--fidelity", type=click.Choice(["moment", "waveform"]), help="Simulator fidelity.")
@click.option("--workers", type=click.IntRange(min=0), default=2, show_default=True,
              help="Dask worker processes of a local cluster; 0 runs in this process.")
@click.option("--scheduler", help="Address of a running Dask scheduler (tcp://host:8786) instead of a local cluster.")
def simulate(
    out: Path, config_file: Path | None, preset_name: str, samples: int | None, chunk_rows: int | None,
    seed: int | None, fidelity: str | None, workers: int, scheduler: str | None,
) -> None:
    """Simulate a labelled dataset and print its raw-error summary.

    Re-running on a complete store of the same configuration only prints the summary; an interrupted
    store resumes where it stopped.
    """
    from mpi_lidar import dataset

    dataset_overrides: dict[str, object] = {"samples": samples, "seed": seed, "chunk_rows": chunk_rows}
    dataset_overrides = {k: v for k, v in dataset_overrides.items() if v is not None}
    if samples is not None and chunk_rows is None:
        base_rows = build_config(config_file, preset_name, {}).dataset.chunk_rows
        dataset_overrides["chunk_rows"] = max(1, min(base_rows, samples))
    simulator = {"fidelity": fidelity} if fidelity else {}
    config = build_config(config_file, preset_name, {"dataset": dataset_overrides, "simulator": simulator})

    from mpi_lidar.cluster import dask_client

    plan = dataset.SamplingPlan.from_config(config)
    store = dataset.create_store(out, config)
    todo = int((~dataset.completed_chunks(store)).sum())
    with _progress() as progress:
        task = progress.add_task("simulating chunks", total=todo)
        if todo and workers > 0:
            with dask_client(scheduler, workers) as client:
                report = dataset.generate(out, config, client, on_chunk=lambda _i: progress.advance(task))
        else:
            report = dataset.generate(out, config, on_chunk=lambda _i: progress.advance(task))
    click.echo(dataset.summarize(out).to_markdown())
    click.echo(f"\n{report.chunks_written} of {plan.chunks} chunks simulated in {report.wall_s:.1f} s "
               f"({report.rows_per_s:,.0f} rows/s, {config.simulator.fidelity} fidelity)")


def _progress() -> Progress:
    return Progress(TextColumn("{task.description}"), BarColumn(), MofNCompleteColumn(), TimeElapsedColumn(),
                    transient=True, disable=not sys.stderr.isatty())


def main() -> None:
    try:
        cli.main(standalone_mode=False)
    except click.ClickException as exc:
        exc.show()
        sys.exit(EXIT_USER_ERROR)
    except click.Abort:
        click.echo("aborted", err=True)
        sys.exit(130)
    except MpiLidarError as exc:
        click.echo(f"error: {exc}", err=True)
        sys.exit(EXIT_USER_ERROR)


if __name__ == "__main__":
    main()
