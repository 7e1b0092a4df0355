"""mpi-lidar train: the final model, with parameters from a file or a study."""

from __future__ import annotations

from pathlib import Path

import click

from mpi_lidar.cli._common import cluster_options, feature_spec, model_options
from mpi_lidar.errors import MpiLidarError
from mpi_lidar.locations import location
from mpi_lidar.terminal import Display, plural


@click.command()
@click.option("--data", required=True, metavar="PATH|URL",
              help="Dataset store (.zarr): a path or a URL (s3://, gs://, az://).")
@click.option("--out", required=True, metavar="PATH|URL",
              help="Model directory to create: a path or a URL (s3://, gs://, az://), published whole, never over a "
                   "model there.")
@click.option("--params", "params_file", type=click.Path(path_type=Path), help="JSON or TOML file of parameters.")
@click.option("--study", "study_name", help="Take the best parameters of this Optuna study.")
@click.option("--storage", help="Optuna storage URL of --study (default: $MPI_LIDAR_STORAGE_URL, else sqlite file "
                                "beside the dataset).")
@model_options
@cluster_options
def train(data: str, out: str, params_file: Path | None, study_name: str | None, storage: str | None,
          feature_set: str | None, target_mode: str | None, geometric: bool | None, workers: int,
          scheduler: str | None) -> None:
    """Train the final XGBoost model through xgboost.dask on the whole train split.

    \b
    Example:
      mpi-lidar train --data runs/d.zarr --out runs/model --study xgboost
    """
    from mpi_lidar.learning import tune as tuning
    from mpi_lidar.learning.model import staged_model
    from mpi_lidar.learning.train import DEFAULT_ROUNDS, train_and_save
    from mpi_lidar.workflows.cluster import dask_client

    if params_file and study_name:
        raise MpiLidarError("give either --params or --study, not both")
    params = load_params(params_file) if params_file else None
    if study_name:
        study = tuning.load_existing_study(tuning.storage_url(storage, data), study_name)
        settings = study.user_attrs.get("settings", {})
        feature_set = feature_set or settings.get("feature_set")
        target_mode = target_mode or settings.get("target_mode")
        geometric = settings.get("geometric", False) if geometric is None else geometric
        params = tuning.best_params(study)
    spec = feature_spec(data, feature_set, target_mode, geometric)
    # A model in an object store is refused there before the training, and published once trained.
    with (staged_model(out) as target, Display() as display, dask_client(scheduler, workers) as client,
          display.step(f"training on {data} (early-stopped, up to {DEFAULT_ROUNDS} rounds)")):
        out_dir, result = train_and_save(client, data, target, spec, params)
    written = out_dir if location(out).is_local else location(out)
    click.echo(f"model written to {written}: {plural(result.best_iteration + 1, 'tree')}, validation MAE "
               f"{1e3 * result.validation_mae_m:.3f} mm, {result.fit_rows:,} rows in {result.wall_s:.1f} s")


def load_params(path: Path) -> dict[str, object]:
    """XGBoost parameters from a JSON or TOML file of scalars."""
    import json
    import tomllib

    from mpi_lidar.learning.train import check_params
    from mpi_lidar.safe_files import read_small_text

    # A regular file of at most 1 MiB, UTF-8: a FIFO or /dev/zero is refused before a byte is read.
    text = read_small_text(path, "parameter file", kind="TOML" if path.suffix == ".toml" else "JSON")
    try:
        params = tomllib.loads(text) if path.suffix == ".toml" else json.loads(text)
    except (ValueError, RecursionError) as exc:  # RecursionError: arrays nested thousands deep
        reason = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        raise MpiLidarError(f"parameter file {path} is not valid {path.suffix[1:] or 'JSON'}: {reason}") from None
    if not isinstance(params, dict):
        raise MpiLidarError(f"parameter file {path} must hold one table of scalar parameters")
    return check_params(params, f"parameter file {path}")
