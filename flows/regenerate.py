"""Prefect flow: regenerate the dataset of a configuration and code version, for schedules.

Each configuration and package version gets its own store, ``<root>/<key>/dataset.zarr`` with
``key = sha256(config_sha256 + package version)[:16]``, so a new configuration or a new release writes a new
store and never touches an older one. A complete store is left as it is and no cluster is started; an absent
or interrupted one is generated (resumed) by :func:`flows.generate_dataset.generate_dataset_flow`. Finally
``<root>/latest`` is pointed at the current key directory.
"""

from __future__ import annotations

from pathlib import Path

from prefect import flow, task
from prefect.cache_policies import NO_CACHE
from prefect.runtime import flow_run

from flows.generate_dataset import build_config_task, generate_dataset_flow
from mpi_lidar.errors import StoreError
from mpi_lidar.simulation import dataset
from mpi_lidar.storage.atomic import atomic_path
from mpi_lidar.workflows.job_options import Workers

STORE_NAME = "dataset.zarr"
LATEST_NAME = "latest"


@task(name="store-complete", cache_policy=NO_CACHE)
def store_complete_task(store: str) -> bool:
    """Whether the store exists and holds every chunk; a damaged store raises rather than being rewritten."""
    if not Path(store).exists():
        return False
    return dataset.dataset_info(store).complete


@task(name="point-latest", cache_policy=NO_CACHE)
def point_latest_task(root: str, key: str) -> str:
    """Point ``<root>/latest`` at ``<root>/<key>`` with one atomic rename of a fresh symlink.

    The link is relative, so the root can be moved or mounted elsewhere. Anything at ``latest`` that is not
    a symlink was made by someone else and is refused.
    """
    latest = Path(root) / LATEST_NAME
    if latest.exists() and not latest.is_symlink():
        raise StoreError(f"{latest} exists and is not a symlink; move it away so 'latest' can be updated")
    with atomic_path(latest, replace=True, what="link") as staging:
        staging.symlink_to(key, target_is_directory=True)
    return str(latest)


@flow(name="regenerate-dataset")
def regenerate_dataset_flow(
    root: str,
    preset: str = "quick",
    config_file: str | None = None,
    workers: Workers = 2,
    scheduler: str | None = None,
) -> dict[str, object]:
    """Make sure ``root`` holds the complete dataset of this configuration and code version.

    Returns ``skipped`` (True when the store was already complete and nothing ran), the store ``path``,
    its ``key``, the ``latest`` link, this ``flow_run_id`` and, when it generated, the ``generation`` result
    of the subflow.
    """
    config = build_config_task(preset, config_file, None, None)
    key = dataset.store_key(config)
    store = str(Path(root) / key / STORE_NAME)
    skipped = store_complete_task(store)
    generation = None
    if not skipped:
        generation = generate_dataset_flow(out=store, preset=preset, config_file=config_file, workers=workers,
                                           scheduler=scheduler)
    latest = point_latest_task(root, key)
    return {"skipped": skipped, "path": store, "key": key, "latest": latest, "generation": generation,
            "flow_run_id": str(flow_run.id)}
