"""mpi-lidar render-scenes: simulated scenes as scan stores with their reference depths."""

from __future__ import annotations

from pathlib import Path

import click

from mpi_lidar.cli._declared import bounded
from mpi_lidar.errors import MpiLidarError
from mpi_lidar.workflows.job_options import Seed


@click.command("render-scenes")
@click.option("--out", "out_dir", type=click.Path(path_type=Path), required=True, help="Directory for the scans.")
@click.option("--scene", "names", multiple=True, help="Scene name (repeatable); default: the demo scenes.")
@click.option("--seed", type=bounded(Seed), default=0, show_default=True)
def render_scenes(out_dir: Path, names: tuple[str, ...], seed: int) -> None:
    """Render simulated scenes (cornered board, multi-object, flat wall, ...) as scan stores with references.

    \b
    Example:
      mpi-lidar render-scenes --out scenes --scene corner --scene flat_wall
    """
    from mpi_lidar.simulation.scenes import DEMO_SCENES, SCENES
    from mpi_lidar.simulation.scenes import render_scenes as render

    unknown = sorted(set(names) - set(SCENES))
    if unknown:
        raise MpiLidarError(f"unknown scene {unknown[0]!r}; choose from {', '.join(SCENES)}")
    for path in render(out_dir, names or DEMO_SCENES, seed=seed):
        click.echo(f"wrote {path}")
