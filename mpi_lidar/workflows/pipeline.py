"""The main job: generate a dataset, tune, train and evaluate, into one run directory.

:func:`run_pipeline` is its one definition, for the command line (:class:`ClusterSteps`, on one Dask cluster)
and for the Prefect flow (``flows.pipeline``, whose steps are subflows and tasks that publish artifacts).

Layout of ``out_dir``: ``dataset.zarr``, ``optuna.db`` (the study), ``model/``, ``report/``, then the demo
scenes rendered into ``scenes/`` and corrected into ``corrected/``. Every step is resumable: a complete
dataset is not regenerated, the study resumes to its trial budget, a model whose card matches the dataset
and the study's best parameters is reused, existing scene scans are kept and corrected scans are skipped.

:class:`ClusterSteps` reports its progress through a :data:`StepDisplay` (the command line's shows a progress
display on a terminal and occasional lines in a log): the dataset's chunks, the study's trials, training and
evaluation (no count: XGBoost reports no rounds across processes) and the demo scans.
"""

from __future__ import annotations

import time
from abc import ABC, abstractmethod
from collections.abc import Callable, Iterator
from contextlib import AbstractContextManager, contextmanager
from dataclasses import dataclass
from pathlib import Path

from distributed import Client

from mpi_lidar.config import Config
from mpi_lidar.correction import CorrectionOptions, ScanOutcome
from mpi_lidar.errors import MpiLidarError
from mpi_lidar.learning import tune
from mpi_lidar.learning.evaluate import Evaluation, evaluate_model
from mpi_lidar.learning.features import DEFAULT_FEATURE_SET, DEFAULT_GEOMETRIC, DEFAULT_TARGET_MODE, FeatureSpec
from mpi_lidar.learning.model import CARD_FILE, load_model, read_card
from mpi_lidar.learning.train import DEFAULT_ROUNDS, train_and_save, xgb_params
from mpi_lidar.reporting.batch_report import write_batch_report
from mpi_lidar.reporting.report import Report, evaluation_report, write_report_to
from mpi_lidar.scans.store import SCAN_SUFFIX
from mpi_lidar.simulation import dataset
from mpi_lidar.simulation.scenes import DEMO_SCENES, render_scenes
from mpi_lidar.workflows.correct_archive import correct_archive
from mpi_lidar.workflows.executor import DaskExecutor
from mpi_lidar.workflows.generate import GenerationReport, generate

STUDY = "xgboost"  # the pipeline's study in its storage

# ``display(description, total)`` shows a step while its block runs and yields the function that counts one of
# its ``total`` items done (None: a step without a count).
StepDisplay = Callable[[str, "int | None"], AbstractContextManager[Callable[[], None]]]


@contextmanager
def no_display(description: str, total: int | None = None) -> Iterator[Callable[[], None]]:
    """The :data:`StepDisplay` that shows nothing."""
    yield lambda: None


@dataclass(frozen=True)
class PipelineResult:
    dataset: GenerationReport
    tuning: tune.TuneReport
    model_dir: Path
    model_reused: bool
    evaluation: Evaluation
    report_dir: Path
    scans: list[ScanOutcome]


class PipelineSteps(ABC):
    """How each step of the main job runs. :func:`run_pipeline` decides what runs, with what, in which order.

    :class:`ClusterSteps` runs the steps on one Dask cluster (the command line); the Prefect flow
    (``flows.pipeline``) runs each as a subflow or task that also publishes its artifacts.
    """

    @abstractmethod
    def generate(self, data: Path, config: Config) -> GenerationReport:
        """Generate (or resume) the dataset store ``data`` of ``config``."""

    @abstractmethod
    def tune(self, storage: str, study: str, settings: tune.TuneSettings, trials: int) -> tune.TuneReport:
        """Run the study to ``trials`` finished trials."""

    @abstractmethod
    def train(self, data: Path, model_dir: Path, spec: FeatureSpec, params: dict[str, object], storage: str,
              study: str) -> None:
        """Train the final model into ``model_dir`` with ``params``, the best of ``study`` in ``storage``."""

    @abstractmethod
    def evaluate(self, data: Path, model_dir: Path, report_dir: Path) -> Evaluation:
        """Evaluate the model on the test split and write the report into ``report_dir``."""

    def demo_scans(self, scene_dir: Path, config: Config) -> list[Path]:
        """The demo scenes as scans (:func:`demo_scans`)."""
        return demo_scans(scene_dir, config)

    @abstractmethod
    def correct(self, scans: list[Path], model_dir: Path, out_dir: Path,
                options: CorrectionOptions) -> list[ScanOutcome]:
        """Correct the scans into ``out_dir`` and write the batch summary there."""


class ClusterSteps(PipelineSteps):
    """Every step on one Dask client: chunks, trials, training and scans are its tasks."""

    def __init__(self, client: Client, display: StepDisplay = no_display) -> None:
        self.client = client
        self.executor = DaskExecutor(client)
        self.display = display

    def generate(self, data: Path, config: Config) -> GenerationReport:
        todo = len(dataset.incomplete_chunks(dataset.create_store(data, config)))
        with self.display("simulating dataset chunks", todo) as advance:
            return generate(data, config, self.executor, on_chunk=lambda _index: advance())

    def tune(self, storage: str, study: str, settings: tune.TuneSettings, trials: int) -> tune.TuneReport:
        todo = max(0, trials - tune.count(tune.open_study(storage, study, settings), *tune.FINISHED))
        with self.display("tuning: Optuna trials", todo) as advance:
            return tune.tune(self.client, storage, study, settings, trials, on_trial=lambda _number: advance())

    def train(self, data: Path, model_dir: Path, spec: FeatureSpec, params: dict[str, object], storage: str,
              study: str) -> None:
        with self.display(f"training the model (early-stopped, up to {DEFAULT_ROUNDS} rounds)", None):
            train_and_save(self.client, data, model_dir, spec, params)

    def evaluate(self, data: Path, model_dir: Path, report_dir: Path) -> Evaluation:
        with self.display("evaluating on the test split", None):
            return evaluate_to_report(data, model_dir, report_dir)[0]

    def demo_scans(self, scene_dir: Path, config: Config) -> list[Path]:
        if not _missing_scenes(scene_dir):
            return demo_scans(scene_dir, config)
        with self.display("rendering the demo scenes", None):
            return demo_scans(scene_dir, config)

    def correct(self, scans: list[Path], model_dir: Path, out_dir: Path,
                options: CorrectionOptions) -> list[ScanOutcome]:
        started = time.perf_counter()
        with self.display("correcting the demo scenes", len(scans)) as advance:
            outcomes = correct_archive([str(p) for p in scans], model_dir, out_dir, options, self.executor,
                                       on_scan=lambda _outcome: advance())
        write_batch_report(outcomes, time.perf_counter() - started, out_dir)
        return outcomes


def run_pipeline(
    steps: PipelineSteps, out_dir: str | Path, config: Config, trials: int, tune_rows: int,
    echo: Callable[[str], None] = print,
) -> PipelineResult:
    """The main job into ``out_dir``, each step run by ``steps``; every step resumes what a previous run left.

    A model directory whose card does not match the dataset, the study's best parameters and the inputs is
    refused (:class:`MpiLidarError`), never overwritten nor silently reused.
    """
    out_dir = Path(out_dir)
    data, model_dir, report_dir = out_dir / "dataset.zarr", out_dir / "model", out_dir / "report"
    generation = steps.generate(data, config)
    echo(f"dataset {data}: {generation.chunks_written} chunks written, {generation.chunks_skipped} already there")

    spec = FeatureSpec(config.frequencies_hz, DEFAULT_FEATURE_SET, DEFAULT_TARGET_MODE, DEFAULT_GEOMETRIC)
    storage = tune.default_storage(data)
    settings = tune.TuneSettings(str(data), spec, tune_rows=min(tune_rows, config.dataset.samples))
    tuning = steps.tune(storage, STUDY, settings, trials)
    assert tuning.best_value_m is not None, "the study has complete trials"
    echo(f"study '{STUDY}': {tuning.trials_run} trials run, best validation MAE {1e3 * tuning.best_value_m:.3f} mm")

    params = tune.best_params(tune.load_existing_study(storage, STUDY))
    reused = _matching_model(model_dir, data, params, spec)
    if not reused:
        steps.train(data, model_dir, spec, params, storage, STUDY)
    echo(f"model {model_dir}: {'reused' if reused else 'trained'}")

    evaluation = steps.evaluate(data, model_dir, report_dir)
    scans = steps.demo_scans(out_dir / "scenes", config)
    outcomes = steps.correct(scans, model_dir, out_dir / "corrected", CorrectionOptions())
    return PipelineResult(generation, tuning, model_dir, reused, evaluation, report_dir, outcomes)


def evaluate_to_report(data: str | Path, model_dir: str | Path, report_dir: str | Path,
                       split: str = "test") -> tuple[Evaluation, Report]:
    """Evaluate the model on a dataset split and write the report (metrics table, error histogram)."""
    model = load_model(model_dir)
    evaluation = evaluate_model(model, data, split)
    report, figures = evaluation_report(evaluation, model.card)
    write_report_to(report, report_dir, figures)
    return evaluation, report


def demo_scans(scene_dir: Path, config: Config) -> list[Path]:
    """The demo scenes as scans, rendered once (existing scans are kept)."""
    missing = _missing_scenes(scene_dir)
    if missing:
        render_scenes(scene_dir, missing, config)
    return [scene_dir / f"{name}{SCAN_SUFFIX}" for name in DEMO_SCENES]


def _missing_scenes(scene_dir: Path) -> tuple[str, ...]:
    return tuple(name for name in DEMO_SCENES if not (scene_dir / f"{name}{SCAN_SUFFIX}").exists())


def _matching_model(model_dir: Path, data: Path, params: dict[str, object], spec: FeatureSpec) -> bool:
    """True if model_dir holds a model of this dataset, parameters and inputs; refuse anything else there."""
    if not model_dir.exists():
        return False
    card_path = model_dir / CARD_FILE
    card = read_card(card_path) if card_path.is_file() else None
    if (card is not None and card.dataset.config_sha256 == dataset.dataset_info(data).config_sha256
            and list(card.feature_names) == spec.names and card.params == xgb_params(params or None)):
        return True
    raise MpiLidarError(f"{model_dir} holds another model (other data, parameters or inputs); move it away to "
                        "retrain")
