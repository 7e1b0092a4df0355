"""Prefect flow: the main job, :func:`mpi_lidar.workflows.pipeline.run_pipeline`, with steps that publish.

The library's pipeline is the one definition of the job (paths, order, tuning settings, the rule that reuses
a matching model and refuses a mismatched model directory); :class:`FlowSteps` runs its steps as the other
flows (generation, tuning and training as subflows; evaluation, the demo scenes and their correction as
tasks of this flow), so every step's artifacts are published. Each step resumes what a previous run left.
"""

from __future__ import annotations

from pathlib import Path

from prefect import flow, get_run_logger, task
from prefect.cache_policies import NO_CACHE

from flows.correct import correct_and_publish
from flows.evaluate import evaluate_task
from flows.generate_dataset import for_sensor, generate_dataset_flow
from flows.train import train_flow
from flows.tune import tune_flow
from mpi_lidar.config import Config, resolve_config
from mpi_lidar.correction import CorrectionOptions, ScanOutcome
from mpi_lidar.learning import tune
from mpi_lidar.learning.evaluate import Evaluation
from mpi_lidar.learning.features import FeatureSpec
from mpi_lidar.workflows.generate import GenerationReport
from mpi_lidar.workflows.job_options import Trials, TuneRows, Workers
from mpi_lidar.workflows.pipeline import PipelineSteps, demo_scans, run_pipeline


@task(name="render-demo-scenes", cache_policy=NO_CACHE)
def demo_scans_task(scene_dir: str, config: Config) -> list[str]:
    return [str(p) for p in demo_scans(Path(scene_dir), config)]


class FlowSteps(PipelineSteps):
    """The pipeline's steps as the flows and tasks of this package, on ``workers`` or at ``scheduler``."""

    def __init__(self, preset: str, config_file: str | None, workers: int, scheduler: str | None,
                 sensor: str | None = None) -> None:
        self.preset, self.config_file, self.workers, self.scheduler = preset, config_file, workers, scheduler
        self.sensor = sensor

    def generate(self, data: Path, config: Config) -> GenerationReport:
        # The subflow resolves the same preset, file and sensor profile into the same config (run_pipeline's).
        run = generate_dataset_flow(out=str(data), preset=self.preset, config_file=self.config_file,
                                    workers=self.workers, scheduler=self.scheduler, sensor=self.sensor)
        return GenerationReport(run["chunks_written"], run["chunks_skipped"], run["rows_written"], run["wall_s"])

    def tune(self, storage: str, study: str, settings: tune.TuneSettings, trials: int) -> tune.TuneReport:
        spec = settings.spec
        run = tune_flow(data=settings.data_path, storage=storage, study=study, trials=trials,
                        tune_rows=settings.tune_rows, feature_set=spec.feature_set, target=spec.target_mode,
                        geometric=spec.geometric, workers=self.workers, scheduler=self.scheduler)
        return tune.TuneReport(study_name=study, **{k: run[k] for k in (
            "trials_run", "complete", "pruned", "failed", "best_value_m", "best_params", "wall_s")})

    def train(self, data: Path, model_dir: Path, spec: FeatureSpec, params: dict[str, object], storage: str,
              study: str) -> None:
        # train_flow takes ``params`` from the study, as run_pipeline did.
        train_flow(data=str(data), out=str(model_dir), study=study, storage=storage, feature_set=spec.feature_set,
                   target=spec.target_mode, geometric=spec.geometric, workers=self.workers, scheduler=self.scheduler)

    def evaluate(self, data: Path, model_dir: Path, report_dir: Path) -> Evaluation:
        evaluation, _ = evaluate_task(str(data), str(model_dir), str(report_dir), "test")
        return evaluation

    def demo_scans(self, scene_dir: Path, config: Config) -> list[Path]:
        return [Path(p) for p in demo_scans_task(str(scene_dir), config)]

    def correct(self, scans: list[Path], model_dir: Path, out_dir: Path,
                options: CorrectionOptions) -> list[ScanOutcome]:
        outcomes, _ = correct_and_publish([str(p) for p in scans], str(model_dir), str(out_dir), options,
                                          self.workers, self.scheduler)
        return outcomes


@flow(name="pipeline")
def pipeline_flow(out: str | None = None, preset: str = "quick", trials: Trials = 6, tune_rows: TuneRows = 20_000,
                  workers: Workers = 2, scheduler: str | None = None, config_file: str | None = None,
                  sensor: str | None = None) -> dict[str, object]:
    """``mpi-lidar pipeline`` as a flow: the same options (``config_file`` is ``--config``), the same run directory
    (``runs/<preset>`` by default).

    ``corrected`` is False when a demo scene failed to correct (its reason is in the published summary).
    """
    config = for_sensor(resolve_config(config_file, preset), sensor)
    steps = FlowSteps(preset, config_file, workers, scheduler, sensor)
    out = out or str(Path("runs") / preset)
    result = run_pipeline(steps, out, config, trials, tune_rows, echo=get_run_logger().info)
    return {"out": out, "best_value_m": result.tuning.best_value_m,
            "corrected": all(o.status != "failed" for o in result.scans)}
