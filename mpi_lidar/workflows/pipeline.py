"""The main job: generate a dataset, tune, train and evaluate, into one run directory, on one cluster.

Layout of ``out_dir``: ``dataset.zarr``, ``optuna.db`` (the study), ``model/``, ``report/``, then the demo
scenes rendered into ``scenes/`` and corrected into ``corrected/``. Every step is resumable: a complete
dataset is not regenerated, the study resumes to its trial budget, a model whose card matches the dataset
and the study's best parameters is reused, existing scene scans are kept and corrected scans are skipped.
"""

from __future__ import annotations

import json
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

from distributed import Client

from mpi_lidar.config import Config
from mpi_lidar.correction import CorrectionOptions, ScanOutcome
from mpi_lidar.errors import MpiLidarError
from mpi_lidar.learning import tune
from mpi_lidar.learning.evaluate import Evaluation, evaluate_model
from mpi_lidar.learning.features import DEFAULT_FEATURE_SET, DEFAULT_GEOMETRIC, DEFAULT_TARGET_MODE, FeatureSpec
from mpi_lidar.learning.model import CARD_FILE, load_model
from mpi_lidar.learning.train import BASE_PARAMS, train_and_save
from mpi_lidar.reporting.report import evaluation_report, write_report
from mpi_lidar.reporting.scan_report import write_batch_report
from mpi_lidar.scans.scan import SCAN_SUFFIX
from mpi_lidar.simulation import dataset
from mpi_lidar.simulation.scenes import DEMO_SCENES, render_scenes
from mpi_lidar.workflows.correct_archive import correct_archive


@dataclass(frozen=True)
class PipelineResult:
    dataset: dataset.GenerationReport
    tuning: tune.TuneReport
    model_dir: Path
    model_reused: bool
    evaluation: Evaluation
    report_dir: Path
    scans: list[ScanOutcome]


def run_pipeline(
    client: Client, out_dir: str | Path, config: Config, trials: int, tune_rows: int,
    echo: Callable[[str], None] = print,
) -> PipelineResult:
    out_dir = Path(out_dir)
    data, model_dir, report_dir = out_dir / "dataset.zarr", out_dir / "model", out_dir / "report"
    generation = dataset.generate(data, config, client)
    echo(f"dataset {data}: {generation.chunks_written} chunks written, {generation.chunks_skipped} already there")

    spec = FeatureSpec(config.frequencies_hz, DEFAULT_FEATURE_SET, DEFAULT_TARGET_MODE, DEFAULT_GEOMETRIC)
    storage = tune.default_storage(data)
    settings = tune.TuneSettings(str(data), spec, tune_rows=min(tune_rows, config.dataset.samples))
    tuning = tune.tune(client, storage, "xgboost", settings, trials)
    echo(f"study 'xgboost': {tuning.trials_run} trials run, best validation MAE {1e3 * tuning.best_value_m:.3f} mm")

    params = tune.best_params(tune.load_existing_study(storage, "xgboost"))
    reused = _matching_model(model_dir, data, params, spec)
    if not reused:
        train_and_save(client, data, model_dir, spec, params)
    echo(f"model {model_dir}: {'reused' if reused else 'trained'}")

    model = load_model(model_dir)
    evaluation = evaluate_model(model, data)
    report, figures = evaluation_report(evaluation, model.card)
    write_report(report, report_dir, figures)

    scans = demo_scans(out_dir / "scenes", config)
    started = time.perf_counter()
    outcomes = correct_archive([str(p) for p in scans], model_dir, out_dir / "corrected", CorrectionOptions(),
                               client)
    write_batch_report(outcomes, time.perf_counter() - started, out_dir / "corrected")
    return PipelineResult(generation, tuning, model_dir, reused, evaluation, report_dir, outcomes)


def demo_scans(scene_dir: Path, config: Config) -> list[Path]:
    """The demo scenes as scans, rendered once (existing scans are kept)."""
    missing = tuple(name for name in DEMO_SCENES if not (scene_dir / f"{name}{SCAN_SUFFIX}").exists())
    if missing:
        render_scenes(scene_dir, missing, config)
    return [scene_dir / f"{name}{SCAN_SUFFIX}" for name in DEMO_SCENES]


def _matching_model(model_dir: Path, data: Path, params: dict[str, object], spec: FeatureSpec) -> bool:
    """True if model_dir holds a model of this dataset, parameters and inputs; refuse anything else there."""
    if not model_dir.exists():
        return False
    card_path = model_dir / CARD_FILE
    card = json.loads(card_path.read_text()) if card_path.is_file() else {}
    same_data = card.get("dataset", {}).get("config_sha256") == dataset.dataset_info(data).config_sha256
    same_inputs = card.get("feature_names") == spec.names
    if same_data and same_inputs and card.get("params") == {**BASE_PARAMS, **params}:
        return True
    raise MpiLidarError(f"{model_dir} holds another model (other data, parameters or inputs); move it away to "
                        "retrain")
