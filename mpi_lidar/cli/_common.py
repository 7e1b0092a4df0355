"""What several commands share: the sensor profile of a simulation, the cluster options, the model options."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING, TypeVar, cast

import click

from mpi_lidar.config import Config
from mpi_lidar.learning.feature_choices import (  # not .features: that imports dask, and --help must be quick
    DEFAULT_FEATURE_SET,
    DEFAULT_GEOMETRIC,
    DEFAULT_TARGET_MODE,
    FEATURE_SETS,
    TARGET_MODES,
)

if TYPE_CHECKING:
    from mpi_lidar.learning.feature_choices import FeatureSet, TargetMode
    from mpi_lidar.learning.features import FeatureSpec

F = TypeVar("F", bound=Callable[..., object])

SENSOR_SIMULATION_HELP = ("Sensor profile (sensor.toml from mpi-lidar calibrate): simulate that sensor, its "
                          "frequencies, noise scale and working range (widened by 15 %), over the preset and file.")


def for_sensor(config: Config, sensor: Path | None) -> Config:
    """The configuration with a sensor profile's frequencies, noise scale and working range (none: as it is)."""
    if sensor is None:
        return config
    from mpi_lidar.calibration.profile import read_profile
    from mpi_lidar.config import validate_overrides

    return validate_overrides(read_profile(sensor).simulation(), config, source=f"sensor profile {sensor}")


def cluster_options(command: F) -> F:
    """--workers and --scheduler, shared by every command that runs on Dask."""
    command = click.option("--scheduler", help="Address of a running Dask scheduler (tcp://host:8786).")(command)
    from mpi_lidar.cli._declared import bounded
    from mpi_lidar.workflows.job_options import Workers

    return click.option("--workers", type=bounded(Workers), default=2, show_default=True,
                        help="Worker processes of a local Dask cluster; 0 runs in this process (ignored with "
                             "--scheduler).")(command)


def model_options(command: F) -> F:
    """--feature-set, --target and --geometric of tune and train (unset: the defaults, or the study's)."""
    command = click.option("--geometric/--no-geometric", default=None,
                           help="Add the scan geometry's rho_ABA and d_AB estimates as inputs (default: "
                                f"{'yes' if DEFAULT_GEOMETRIC else 'no'}, or the study's); such a model corrects "
                                "only scans with geometry.")(command)
    command = click.option("--target", "target_mode", type=click.Choice(TARGET_MODES),
                           help=f"Target mode (default {DEFAULT_TARGET_MODE}, or the study's).")(command)
    return click.option("--feature-set", type=click.Choice(FEATURE_SETS),
                        help=f"Model inputs (default {DEFAULT_FEATURE_SET}, or the study's).")(command)


def feature_spec(data: str | Path, feature_set: str | None, target_mode: str | None,
                 geometric: bool | None = None) -> FeatureSpec:
    """The model's inputs and target on the dataset ``data``'s frequencies; None: the default."""
    from mpi_lidar.learning.features import FeatureSpec
    from mpi_lidar.simulation import dataset

    info = dataset.dataset_info(data)
    return FeatureSpec(info.frequencies_hz, cast("FeatureSet", feature_set or DEFAULT_FEATURE_SET),
                       cast("TargetMode", target_mode or DEFAULT_TARGET_MODE),
                       DEFAULT_GEOMETRIC if geometric is None else geometric)
