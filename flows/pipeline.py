"""Prefect flow: the main job as subflows, so every step's artifacts are published.

Generate the dataset, tune, train, evaluate on the test split, then render the demo scenes and correct
them; each step resumes what a previous run left (see :mod:`mpi_lidar.workflows.pipeline`).
"""

from __future__ import annotations

from pathlib import Path

from prefect import flow, task
from prefect.cache_policies import NO_CACHE

from flows.correct import correct_archive_flow
from flows.evaluate import evaluate_flow
from flows.generate_dataset import generate_dataset_flow
from flows.train import train_flow
from flows.tune import tune_flow
from mpi_lidar.config import resolve_config
from mpi_lidar.workflows.pipeline import demo_scans


@task(name="render-demo-scenes", cache_policy=NO_CACHE)
def demo_scans_task(scene_dir: str, preset: str) -> list[str]:
    return [str(p) for p in demo_scans(Path(scene_dir), resolve_config(None, preset))]


@flow(name="pipeline")
def pipeline_flow(out: str = "runs/quick", preset: str = "quick", trials: int = 6, tune_rows: int = 20_000,
                  workers: int = 2, scheduler: str | None = None) -> dict[str, object]:
    root = Path(out)
    data, model = str(root / "dataset.zarr"), root / "model"
    generate_dataset_flow(out=data, preset=preset, workers=workers, scheduler=scheduler)
    tuned = tune_flow(data=data, trials=trials, tune_rows=tune_rows, workers=workers, scheduler=scheduler)
    if not model.exists():
        train_flow(data=data, out=str(model), study="xgboost", workers=workers, scheduler=scheduler)
    evaluate_flow(data=data, model=str(model), report=str(root / "report"))
    scans = demo_scans_task(str(root / "scenes"), preset)
    corrected = correct_archive_flow(scans=scans, model=str(model), out=str(root / "corrected"), workers=workers,
                                     scheduler=scheduler, return_state=True)
    return {"best_value_m": tuned["best_value_m"], "corrected": corrected.is_completed()}
