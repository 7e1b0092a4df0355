"""Prefect flow: train the final XGBoost model through xgboost.dask and publish its card."""

from __future__ import annotations

import json

from prefect import task
from prefect.artifacts import create_markdown_artifact
from prefect.cache_policies import NO_CACHE

from flows.tune import SecretsMaskedFlow, flow_storage
from mpi_lidar.learning import tune
from mpi_lidar.learning.features import DEFAULT_FEATURE_SET, DEFAULT_GEOMETRIC, DEFAULT_TARGET_MODE, FeatureSpec
from mpi_lidar.learning.model import CARD_FILE, read_card
from mpi_lidar.learning.train import train_and_save
from mpi_lidar.simulation import dataset
from mpi_lidar.workflows.cluster import dask_client
from mpi_lidar.workflows.job_options import Workers

CARD_ARTIFACT_KEY = "model-card"


@task(name="best-params", cache_policy=NO_CACHE)
def best_params_task(storage: str, study: str) -> tuple[dict[str, object], dict[str, object]]:
    """The study's best parameters and the settings it was tuned with."""
    found = tune.load_existing_study(storage, study)
    return tune.best_params(found), dict(found.user_attrs.get("settings", {}))


@task(name="train-model", cache_policy=NO_CACHE)
def train_task(data: str, out: str, spec: FeatureSpec, params: dict[str, object] | None, workers: int,
               scheduler: str | None) -> str:
    with dask_client(scheduler, workers) as client:
        out_dir, _ = train_and_save(client, data, out, spec, params)
    return str(out_dir)


@task(name="publish-card", cache_policy=NO_CACHE)
def publish_card_task(model_dir: str) -> str:
    card = read_card(f"{model_dir}/{CARD_FILE}")  # a URL's text too: a Path would fold its s3:// to s3:/
    shown = {"feature_set": card.feature_set, "target_mode": card.target_mode, "geometric": card.geometric,
             "num_boost_round": card.num_boost_round, "metrics": card.metrics.model_dump(),
             "training": card.training.model_dump(), "params": card.params}
    lines = ["| card field | value |", "|---|---|"]
    for key, value in shown.items():
        lines.append(f"| {key} | `{json.dumps(value, sort_keys=True)}` |")
    lines.append(f"| dataset | `{card.dataset.config_sha256[:12]}` ({card.dataset.samples:,} rows) |")
    markdown = "\n".join(lines)
    create_markdown_artifact(markdown=markdown, key=CARD_ARTIFACT_KEY, description=f"Model {model_dir}")
    return markdown


def _geometric(requested: bool | None, settings: dict[str, object], study: str | None) -> bool:
    """Explicit choice first, then the study's inputs (a study without the key was pixel-wise), then the default."""
    if requested is not None:
        return requested
    return bool(settings.get("geometric", False)) if study else DEFAULT_GEOMETRIC


def train_flow(data: str, out: str, study: str | None = None, storage: str | None = None,
               feature_set: str | None = None, target: str | None = None, geometric: bool | None = None,
               workers: Workers = 2, scheduler: str | None = None, storage_secret: str | None = None,
               ) -> dict[str, object]:
    """Train on the whole train split with the study's best parameters (or the defaults).

    ``storage`` must not carry a password (flows/tune.py says where one comes from); ``storage_secret`` names a
    Prefect Secret block that holds the study's storage URL."""
    params, settings = (best_params_task(flow_storage(storage, storage_secret, data), study) if study
                        else (None, {}))
    spec = FeatureSpec(dataset.dataset_info(data).frequencies_hz,
                       feature_set or settings.get("feature_set") or DEFAULT_FEATURE_SET,
                       target or settings.get("target_mode") or DEFAULT_TARGET_MODE,
                       _geometric(geometric, settings, study))
    model_dir = train_task(data, out, spec, params, workers, scheduler)
    publish_card_task(model_dir)
    return {"model_dir": model_dir}


# The flow keeps its function's name: a deployment's entrypoint is flows/train.py:train_flow. Its recorded
# parameters have any password masked, and the flow then refuses it.
train_flow = SecretsMaskedFlow(train_flow, name="train")
