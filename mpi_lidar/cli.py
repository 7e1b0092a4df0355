"""Command line: mpi-lidar pipeline | simulate | tune | train | evaluate. A user error is one line on stderr, exit 2."""

from __future__ import annotations

import os
import sys
import traceback
from pathlib import Path
from typing import TYPE_CHECKING, cast

import click

from mpi_lidar.config import PRESETS, Config, resolve_config
from mpi_lidar.correction.gate_names import GATES
from mpi_lidar.errors import EXIT_FAILURE, EXIT_USER_ERROR, MpiLidarError, environment_fault, write_error_log
from mpi_lidar.learning.feature_choices import (  # not .features: that imports dask, and --help must be quick
    DEFAULT_FEATURE_SET,
    DEFAULT_GEOMETRIC,
    DEFAULT_TARGET_MODE,
    FEATURE_SETS,
    TARGET_MODES,
)
from mpi_lidar.redact import install_log_redaction, redact
from mpi_lidar.reporting.output_levels import DEFAULT_OUTPUTS, OUTPUT_LEVELS
from mpi_lidar.terminal import Display, plural, print_table

if TYPE_CHECKING:
    from mpi_lidar.correction import ScanOutcome
    from mpi_lidar.learning.feature_choices import FeatureSet, TargetMode
    from mpi_lidar.learning.features import FeatureSpec


@click.group(context_settings={"help_option_names": ["-h", "--help"]})
@click.version_option(package_name="mpi-lidar")
@click.option("--debug", is_flag=True, expose_value=False,
              help="Print the traceback of an unexpected error (it is always written to a log file).")
def cli() -> None:
    """Multipath-interference suppression for AMCW coaxial scanning LiDAR."""


SENSOR_SIMULATION_HELP = ("Sensor profile (sensor.toml from mpi-lidar calibrate): simulate that sensor, its "
                          "frequencies, noise scale and working range (widened by 15 %), over the preset and file.")


def for_sensor(config: Config, sensor: Path | None) -> Config:
    """The configuration with a sensor profile's frequencies, noise scale and working range (none: as it is)."""
    if sensor is None:
        return config
    from mpi_lidar.config import validate_overrides
    from mpi_lidar.correction.profile import read_profile

    return validate_overrides(read_profile(sensor).simulation(), config, source=f"sensor profile {sensor}")


@cli.command()
@click.option("--out", "out", type=click.Path(path_type=Path), required=True, help="Dataset store to write (.zarr).")
@click.option("--config", "config_file", type=click.Path(path_type=Path), help="TOML file overriding the preset.")
@click.option("--preset", "preset_name", type=click.Choice(sorted(PRESETS)), default="quick", show_default=True)
@click.option("--samples", type=int, help="Number of rows (overrides the preset and file).")
@click.option("--chunk-rows", type=int, help="Rows per chunk.")
@click.option("--seed", type=int, help="Seed of the sampling plan.")
@click.option("--fidelity", type=click.Choice(["moment", "waveform"]), help="Simulator fidelity.")
@click.option("--sensor", "sensor", type=click.Path(path_type=Path), default=None, help=SENSOR_SIMULATION_HELP)
@click.option("--workers", type=click.IntRange(min=0), default=2, show_default=True,
              help="Dask worker processes of a local cluster; 0 runs in this process.")
@click.option("--scheduler", help="Address of a running Dask scheduler (tcp://host:8786) instead of a local cluster.")
def simulate(
    out: Path, config_file: Path | None, preset_name: str, samples: int | None, chunk_rows: int | None,
    seed: int | None, fidelity: str | None, sensor: Path | None, workers: int, scheduler: str | None,
) -> None:
    """Simulate a labelled dataset and print its raw-error summary.

    \b
    Example:
      mpi-lidar simulate --out runs/d.zarr --samples 20000 --workers 2

    Re-running on a complete store of the same configuration only prints the summary; an interrupted
    store resumes where it stopped.
    """
    from mpi_lidar.simulation import dataset

    config = for_sensor(resolve_config(config_file, preset_name, samples=samples, chunk_rows=chunk_rows, seed=seed,
                                       fidelity=fidelity), sensor)

    from mpi_lidar.workflows.executor import InProcess, dask_executor
    from mpi_lidar.workflows.generate import generate

    plan = dataset.SamplingPlan.from_config(config)
    todo = len(dataset.incomplete_chunks(dataset.create_store(out, config)))
    with Display() as display, display.step("simulating chunks", todo) as advance:
        with InProcess() if not todo or workers == 0 else dask_executor(scheduler, workers) as executor:
            report = generate(out, config, executor, on_chunk=lambda _i: advance())
    summary = dataset.summarize(out)
    click.echo(f"dataset {summary.path}: {plural(summary.samples, 'row')} ({summary.train:,} train, "
               f"{summary.test:,} test), config {summary.config_sha256[:12]}")
    print_table(("frequency", "raw MAE [mm]", "raw RMSE [mm]", "noise-only MAE [mm]"),
                [(f"{f / 1e6:g} MHz", f"{1e3 * mae:.3f}", f"{1e3 * rmse:.3f}", f"{1e3 * noise:.3f}")
                 for f, mae, rmse, noise in zip(summary.frequencies_hz, summary.mae_m, summary.rmse_m,
                                                summary.noise_only_mae_m, strict=True)])
    click.echo(f"noise-only: the same scenes without the A -> B -> A path, first {summary.noise_only_rows:,} rows")
    click.echo(f"{report.chunks_written} of {plural(plan.chunks, 'chunk')} simulated in {report.wall_s:.1f} s "
               f"({report.rows_per_s:,.0f} rows/s, {config.simulator.fidelity} fidelity)")


def cluster_options(command):
    """--workers and --scheduler, shared by every command that runs on Dask."""
    command = click.option("--scheduler", help="Address of a running Dask scheduler (tcp://host:8786).")(command)
    return click.option("--workers", type=click.IntRange(min=0), default=2, show_default=True,
                        help="Worker processes of a local Dask cluster; 0 runs in this process (ignored with "
                             "--scheduler).")(command)


def model_options(command):
    command = click.option("--geometric/--no-geometric", default=None,
                           help="Add the scan geometry's rho_ABA and d_AB estimates as inputs (default: "
                                f"{'yes' if DEFAULT_GEOMETRIC else 'no'}, or the study's); such a model corrects "
                                "only scans with geometry.")(command)
    command = click.option("--target", "target_mode", type=click.Choice(TARGET_MODES),
                           help=f"Target mode (default {DEFAULT_TARGET_MODE}, or the study's).")(command)
    return click.option("--feature-set", type=click.Choice(FEATURE_SETS),
                        help=f"Model inputs (default {DEFAULT_FEATURE_SET}, or the study's).")(command)


def feature_spec(data: Path, feature_set: str | None, target_mode: str | None,
                 geometric: bool | None = None) -> FeatureSpec:
    from mpi_lidar.learning.features import FeatureSpec
    from mpi_lidar.simulation import dataset

    info = dataset.dataset_info(data)
    return FeatureSpec(info.frequencies_hz, cast("FeatureSet", feature_set or DEFAULT_FEATURE_SET),
                       cast("TargetMode", target_mode or DEFAULT_TARGET_MODE),
                       DEFAULT_GEOMETRIC if geometric is None else geometric)


@cli.command()
@click.option("--data", type=click.Path(path_type=Path), required=True, help="Dataset store (.zarr).")
@click.option("--storage", help="Optuna storage URL (default: $MPI_LIDAR_STORAGE_URL, else sqlite file optuna.db "
                                "beside the dataset).")
@click.option("--study", "study_name", default="xgboost", show_default=True, help="Study name in the storage.")
@click.option("--trials", type=click.IntRange(min=1), default=30, show_default=True,
              help="Finished trials the study should hold; a re-run resumes or extends it.")
@click.option("--tune-rows", type=click.IntRange(min=100), default=100_000, show_default=True,
              help="Train rows each trial learns from.")
@model_options
@cluster_options
def tune(data: Path, storage: str | None, study_name: str, trials: int, tune_rows: int, feature_set: str | None,
         target_mode: str | None, geometric: bool | None, workers: int, scheduler: str | None) -> None:
    """Tune XGBoost with Optuna TPE, trials running in parallel on Dask workers.

    \b
    Example:
      mpi-lidar tune --data runs/d.zarr --trials 30 --storage postgresql://user@db-host/optuna
    """
    from mpi_lidar.learning import tune as tuning
    from mpi_lidar.workflows.cluster import dask_client

    storage = tuning.storage_url(storage, data)
    settings = tuning.TuneSettings(str(data), feature_spec(data, feature_set, target_mode, geometric),
                                   tune_rows=tune_rows)
    study = tuning.open_study(storage, study_name, settings)
    todo = max(0, trials - tuning.count(study, *tuning.FINISHED))
    with Display() as display, dask_client(scheduler, workers) as client, display.step("trials", todo) as advance:
        report = tuning.tune(client, storage, study_name, settings, trials, on_trial=lambda _n: advance())
    click.echo(f"study {study_name!r} in {tuning.masked(storage)}: {plural(report.trials_run, 'trial')} run in "
               f"{report.wall_s:.1f} s; {report.complete} complete, {report.pruned} pruned, {report.failed} failed")
    if report.best_value_m is not None:
        click.echo(f"best validation MAE {1e3 * report.best_value_m:.3f} mm with {report.best_params}")


@cli.command()
@click.option("--data", type=click.Path(path_type=Path), required=True, help="Dataset store (.zarr).")
@click.option("--out", type=click.Path(path_type=Path), required=True, help="Model directory to create.")
@click.option("--params", "params_file", type=click.Path(path_type=Path), help="JSON or TOML file of parameters.")
@click.option("--study", "study_name", help="Take the best parameters of this Optuna study.")
@click.option("--storage", help="Optuna storage URL of --study (default: $MPI_LIDAR_STORAGE_URL, else sqlite file "
                                "beside the dataset).")
@model_options
@cluster_options
def train(data: Path, out: Path, params_file: Path | None, study_name: str | None, storage: str | None,
          feature_set: str | None, target_mode: str | None, geometric: bool | None, workers: int,
          scheduler: str | None) -> None:
    """Train the final XGBoost model through xgboost.dask on the whole train split.

    \b
    Example:
      mpi-lidar train --data runs/d.zarr --out runs/model --study xgboost
    """
    from mpi_lidar.learning import tune as tuning
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
    with (Display() as display, dask_client(scheduler, workers) as client,
          display.step(f"training on {data} (early-stopped, up to {DEFAULT_ROUNDS} rounds)")):
        out_dir, result = train_and_save(client, data, out, spec, params)
    click.echo(f"model written to {out_dir}: {plural(result.best_iteration + 1, 'tree')}, validation MAE "
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


@cli.command()
@click.option("--data", type=click.Path(path_type=Path), required=True, help="Dataset store (.zarr).")
@click.option("--model", "model_dir", type=click.Path(path_type=Path), required=True, help="Model directory.")
@click.option("--out", "--report", "report_dir", type=click.Path(path_type=Path), required=True,
              help="Report directory (--report is the older name).")
@click.option("--split", type=click.Choice(["test", "train"]), default="test", show_default=True)
def evaluate(data: Path, model_dir: Path, report_dir: Path, split: str) -> None:
    """Evaluate a model on a dataset split: metrics table, error histogram, report files.

    \b
    Example:
      mpi-lidar evaluate --data runs/d.zarr --model runs/model --out runs/report
    """
    from mpi_lidar.reporting.report import Table
    from mpi_lidar.workflows.pipeline import evaluate_to_report

    with Display() as display, display.step(f"evaluating on the {split} split"):
        _, report = evaluate_to_report(data, model_dir, report_dir, split)
    metrics = next(block for block in report.blocks if isinstance(block, Table))
    print_table(metrics.headers, metrics.rows)
    click.echo(f"report written to {report_dir}")


@cli.command()
@click.option("--out", "out_dir", type=click.Path(path_type=Path), default=None,
              help="Run directory: dataset.zarr, optuna.db, model/, report/ (default: runs/<preset>).")
@click.option("--config", "config_file", type=click.Path(path_type=Path), help="TOML file overriding the preset.")
@click.option("--preset", "preset_name", type=click.Choice(sorted(PRESETS)), default="quick", show_default=True)
@click.option("--trials", type=click.IntRange(min=1), default=6, show_default=True, help="Tuning budget.")
@click.option("--tune-rows", type=click.IntRange(min=100), default=20_000, show_default=True)
@click.option("--sensor", "sensor", type=click.Path(path_type=Path), default=None, help=SENSOR_SIMULATION_HELP)
@cluster_options
def pipeline(out_dir: Path, config_file: Path | None, preset_name: str, trials: int, tune_rows: int,
             sensor: Path | None, workers: int, scheduler: str | None) -> None:
    """The main job: simulate, tune, train and evaluate into one run directory (resumable).

    \b
    Example:
      mpi-lidar pipeline --preset quick --out runs/quick
    """
    from mpi_lidar.workflows.cluster import dask_client
    from mpi_lidar.workflows.pipeline import ClusterSteps, run_pipeline

    config = for_sensor(resolve_config(config_file, preset_name), sensor)
    out_dir = out_dir or Path("runs") / preset_name
    with Display() as display, dask_client(scheduler, workers) as client:
        result = run_pipeline(ClusterSteps(client, display.step), out_dir, config, trials, tune_rows,
                              echo=display.echo)
    metrics = result.evaluation.metrics
    raw, corrected = metrics[result.evaluation.raw_label], metrics["corrected (XGBoost)"]
    click.echo(f"test split: {result.evaluation.raw_label} MAE {1e3 * raw.mae_m:.3f} mm -> corrected "
               f"{1e3 * corrected.mae_m:.3f} mm; report in {result.report_dir}/report.html")
    for outcome in result.scans:
        masked = outcome.metrics.get("masked region", {})
        change = (f"masked MAE {1e3 * masked['raw_mae_m']:.3f} -> {1e3 * masked['corrected_mae_m']:.3f} mm"
                  if masked else outcome.reason)
        click.echo(f"scene {outcome.name}: {outcome.status}, {change}; {outcome.output}/report.html")


@cli.command()
@click.argument("scans", nargs=-1, required=True)
@click.option("--model", "model_dir", type=click.Path(path_type=Path), required=True, help="Model directory.")
@click.option("--out", "out_dir", type=click.Path(path_type=Path), required=True, help="Output directory.")
@click.option("--gate", type=click.Choice(GATES), default="geometry", show_default=True,
              help="Which valid pixels get corrected: where the scan's geometry allows multipath (geometry; "
                   "on scans without geometry a pixel-wise model corrects every valid pixel and a geometric model, "
                   "the default, leaves them as measured: status unchanged), every valid pixel (all), or "
                   "frequency disagreement (consistency).")
@click.option("--min-bias-mm", type=click.FloatRange(min=0), default=None,
              help="Geometry gate: correct pixels whose expected multipath bias reaches this. [mm] "
                   "(default 4; 1 suits geometric models on weak multipath, see docs/results/scenes.md)")
@click.option("--footprint-area-m2", default=None, metavar="auto|A",
              help="Effective receiver footprint of your sensor, which scales the geometric coupling [m^2], or "
                   "auto: each scan measures its own from its facing surfaces, and pixels that depend on an "
                   "estimate that is not significant are not corrected (flag uncalibrated). "
                   "(default: the --sensor profile's, else auto)")
@click.option("--sensor", "sensor", type=click.Path(path_type=Path), default=None,
              help="Sensor profile (sensor.toml from mpi-lidar calibrate): footprint and the saturation and "
                   "no-return thresholds; --footprint-area-m2 overrides its footprint.")
@click.option("--amplitude-scale", default=None, metavar="auto|N",
              help="The scanner's amplitude unit per V^2 (e.g. 4000 for amplitudes in counts of 1/4000 V^2): "
                   "amplitudes are divided by it before anything reads them; auto: each scan measures its own "
                   "on its flat surfaces, and one that cannot is left as measured (status unserved). "
                   "(default: the --sensor profile's, else 1: V^2)")
@click.option("--baseline", type=click.Choice(["fused", "raw"]), default="fused", show_default=True,
              help="What the valid pixels the model does not correct get: fused, their frequencies' depths fused "
                   "by inverse variance where they agree within noise (about 0.7 of the highest frequency's "
                   "noise); raw, the highest frequency's depth as measured.")
@click.option("--max-invalid-share", type=click.FloatRange(0, 1), default=None,
              help="A scan with more invalid pixels (not finite, no return, saturated, inconsistent) than this "
                   "share is 'degraded'. (default 0.5)")
@click.option("--fail-on", "fail_on", type=click.Choice(["degraded", "unchanged", "failed"]), multiple=True,
              help="Exit 1 (after writing the summary) when a scan has this status; repeatable. "
                   "A failed scan always does, and an unserved one unless --allow-unserved.")
@click.option("--allow-unserved", is_flag=True,
              help="Exit 0 when the model cannot serve a scan (status unserved: out of its range, amplitudes in "
                   "another unit, no geometry for a geometric model); its outputs keep the pixels as measured.")
@click.option("--outputs", type=click.Choice(OUTPUT_LEVELS), default=DEFAULT_OUTPUTS, show_default=True,
              help="What each scan writes: corrected.zarr, metrics.json, report, corrected.laz and a small "
                   "thumbnail (light); "
                   "only corrected.zarr and metrics.json (data); or also maps, error histogram, point-cloud "
                   "views, a 3-D view and point clouds (full, several times slower). A scan already corrected at a "
                   "lower level is corrected again to add the rest.")
# The formats of mpi_lidar.scans.pointcloud.PointCloudFormat, written out: importing it would load laspy for --help.
@click.option("--point-cloud", "point_clouds", type=click.Choice(["las", "laz", "ply"]), multiple=True,
              help="Write the corrected point cloud in this format at any --outputs level; repeatable: "
                   "corrected.las / corrected.laz (LAS 1.4, the raw range an extra dimension) or raw.ply and "
                   "corrected.ply, each with named fields per point. Default: laz at light, ply and laz at full, "
                   "none at data.")
@click.option("--workers", type=click.IntRange(min=0), default=None,
              help="Worker processes of a local Dask cluster, each correcting scans of its own: for a machine "
                   "with many more cores than one process keeps busy. Default (or 0): this process, which puts "
                   "every core on each scan (on 2 cores 1.2-1.5 times as fast as 2 workers).")
@click.option("--scheduler", help="Address of a running Dask scheduler (tcp://host:8786).")
def correct(scans: tuple[str, ...], model_dir: Path, out_dir: Path, gate: str, min_bias_mm: float | None,
            footprint_area_m2: str | None, sensor: Path | None, amplitude_scale: str | None, baseline: str,
            max_invalid_share: float | None,
            fail_on: tuple[str, ...], allow_unserved: bool,
            outputs: str, point_clouds: tuple[str, ...], workers: int | None, scheduler: str | None) -> None:
    """Correct scans (stores, directories or globs) in batch; one report per scan and a batch summary.

    \b
    Example:
      mpi-lidar correct 'archive/2026-11-*/*.scan.zarr' --model runs/model --out corrected --fail-on degraded

    Each scan ends corrected, unchanged (no pixel corrected), degraded (too many invalid pixels), unserved
    (the model cannot serve it: the reason says which command helps), skipped (already done) or failed. Exit 1
    when a scan failed, is unserved (unless --allow-unserved) or has a --fail-on status; 2 on a user error.
    """
    import time

    from mpi_lidar.correction import CorrectionOptions
    from mpi_lidar.correction.profile import profile_options
    from mpi_lidar.reporting.batch_report import write_batch_report
    from mpi_lidar.workflows.correct_archive import (
        correct_archive,
        expand_archive,
        failing_outcomes,
        failure_line,
    )
    from mpi_lidar.workflows.executor import InProcess, dask_executor

    options = CorrectionOptions.from_cli(gate=gate, min_bias_mm=min_bias_mm, footprint_area_m2=footprint_area_m2,
                                         max_invalid_share=max_invalid_share, amplitude_scale=amplitude_scale,
                                         baseline=baseline, **profile_options(sensor))
    started = time.perf_counter()
    here = not scheduler and not workers
    total = len(expand_archive(list(scans)))
    def summarise(outcomes: list[ScanOutcome]) -> Path:  # while the batch still holds out_dir
        return write_batch_report(outcomes, time.perf_counter() - started, out_dir)

    with Display() as display, display.step("correcting scans", total) as advance:
        with InProcess() if here else dask_executor(scheduler, workers or 2) as executor:
            summaries: list[Path] = []
            outcomes = correct_archive(list(scans), model_dir, out_dir, options, executor,
                                       on_scan=lambda outcome: advance(f"{outcome.name}: {outcome.status}"),
                                       outputs=outputs, point_clouds=point_clouds or None,
                                       on_done=lambda done: summaries.append(summarise(done)))
    wall_s = time.perf_counter() - started
    summary = summaries[0]
    print_batch(outcomes, wall_s, summary)
    failing = failing_outcomes(outcomes, fail_on, allow_unserved)
    for outcome in failing:
        click.echo(f"error: {failure_line(outcome)}", err=True)
    if failing:
        sys.exit(1)


def print_batch(outcomes: list[ScanOutcome], wall_s: float, summary_dir: Path) -> None:
    """The batch on the terminal: a line counting the statuses, a table of the scans, where the summary is.

    The same figures as the summary's report (``mpi_lidar.reporting.batch_report``), without its source paths and
    links: each scan's outputs are named by their directory.
    """
    from mpi_lidar.correction import ScanStatus
    from mpi_lidar.correction.outcome import invalid_share
    from mpi_lidar.reporting.batch_report import GATED_OUT

    def mm(metrics: dict[str, float], key: str) -> str:
        value = metrics.get(key) if isinstance(metrics, dict) else None
        return f"{1e3 * value:.3f}" if isinstance(value, int | float) else ""

    def change(metrics: dict[str, float]) -> str:
        raw, corrected = mm(metrics, "raw_mae_m"), mm(metrics, "corrected_mae_m")
        return f"{raw} -> {corrected}" if raw and corrected else ""

    rows = []
    for o in outcomes:
        total = max(sum(o.counts.values()), 1)
        gated = sum(o.counts.get(name, 0) for name in GATED_OUT)
        reason = f"{o.reason} ({o.kept_status})" if o.kept_status else o.reason
        rows.append((o.name, o.status, f"{100 * gated / total:.1f} %" if o.counts else "",
                     f"{100 * invalid_share(o.counts):.1f} %" if o.counts else "",
                     change(o.metrics.get("whole map", {})), change(o.metrics.get("masked region", {})),
                     f"{o.seconds:.2f}", o.output, "; ".join(n for n in (reason, *o.notes) if n)))
    labels = {ScanStatus.SKIPPED: "already done"}
    counted = ", ".join(f"{n} {labels.get(status, status.value)}" for status in ScanStatus
                        if (n := sum(o.status == status for o in outcomes)))
    click.echo(f"{plural(len(outcomes), 'scan')} in {wall_s:.1f} s" + (f": {counted}" if counted else ""))
    print_table(("scan", "status", "gated out", "invalid", "MAE [mm]", "masked MAE [mm]", "seconds", "outputs",
                 "notes"), rows, clip=("notes",))
    click.echo(f"summary: {summary_dir / 'report.html'}")


@cli.command()
@click.argument("scans", nargs=-1, required=True)
@click.option("--out", type=click.Path(path_type=Path), required=True, help="Sensor profile to write (.toml).")
@click.option("--no-reference", is_flag=True,
              help="Measure against each scan's own surfaces even where it has a reference depth.")
def calibrate(scans: tuple[str, ...], out: Path, no_reference: bool) -> None:
    """Measure your sensor's receiver footprint on its scans and write a sensor profile for correct --sensor.

    \b
    Example:
      mpi-lidar calibrate 'archive/corners/*.scan.zarr' --out sensor.toml

    Each scan's footprint comes from the depth and amplitude near its facing surfaces (against its reference
    depth where it has one); the estimates are pooled by their uncertainty. Scans of corners work best. Nothing
    is written when the pooled estimate is not significant (exit 2).
    """
    from mpi_lidar.workflows.calibrate import calibrate_scans, describe, describe_scale

    profile, _ = calibrate_scans(list(scans), out, use_reference=not no_reference,
                                 on_scan=lambda r: click.echo(f"{r.source}: {describe(r.estimate)}; "
                                                              f"{describe_scale(r.scale)}"))
    sigma = profile.calibration["sigma_m2"] if profile.calibration else float("nan")
    click.echo(f"footprint {profile.footprint_area_m2:.4g} +- {sigma:.2g} m^2; amplitude unit "
               f"{profile.amplitude_scale:.4g} per V^2; noise scale "
               + ("not measured" if profile.noise_scale is None else f"{profile.noise_scale:.3g}")
               + _offsets_said(profile.frequency_offsets_m, profile.window_leakage_removed)
               + (f"; range {profile.range_m[0]:.2f}-{profile.range_m[1]:.2f} m" if profile.range_m else "")
               + f"; sensor profile written to {out}")


def _offsets_said(offsets_m: tuple[float, ...] | None, window_leakage_removed: bool | None) -> str:
    """What calibrate says of the frequencies' offsets and the window's leakage."""
    if offsets_m is None:
        return "; frequency offsets not measured"
    from mpi_lidar.correction.correct import offsets_mm

    listed = offsets_mm(offsets_m)
    leakage = "removed first" if window_leakage_removed else "left in"
    return f"; frequency offsets {listed} mm (the integration window's leakage {leakage})"


@cli.command("import-scan")
@click.argument("sources", nargs=-1, required=True)
@click.option("--out", type=click.Path(path_type=Path), required=True,
              help="Scan store to write (X.scan.zarr) for one file, or a directory: OUT/<name>.scan.zarr per file.")
@click.option("--frequencies", help="Comma-separated frequencies in Hz, if the files do not hold frequencies_hz.")
@click.option("--var", "variables", multiple=True, metavar="NAME=VARIABLE",
              help="Read the scan array NAME (depth, amplitude, taps, azimuth_rad, elevation_rad, azimuth_deg, "
                   "elevation_deg, reference_depth, frequencies_hz, ...) from the file's VARIABLE (array of an "
                   ".npz); ignore=VAR1,VAR2 leaves variables out on purpose; repeatable. A variable neither known nor "
                   "mapped is refused; only regular files of at most 2 GiB are read, and all stores are written or "
                   "none.")
@click.option("--depths", type=click.Choice(["wrapped", "unwrapped"]), default="wrapped", show_default=True,
              help="wrapped: each frequency's depth lies in [0, c/2f), as its phase measures it (correction "
                   "unwraps them into one range, out to 24 m at 12.5-31.25 MHz); unwrapped: the scanner gives "
                   "one range per frequency already.")
def import_scan(sources: tuple[str, ...], out: Path, frequencies: str | None, variables: tuple[str, ...],
                depths: str) -> None:
    """Import scans from .npz archives or NetCDF/HDF5 files (.nc, .h5, .hdf5): files, directories or globs.

    \b
    Example:
      mpi-lidar import-scan 'day1/*.nc' --out scans/day1 --var depth=range_m --var amplitude=intensity

    Each file holds depth and amplitude (F, H, W), or taps (F, 4, H, W), plus optional geometry and reference,
    named as in a scan store or mapped with --var (e.g. --var depth=range_m --var amplitude=intensity).
    Every file is read and checked before anything is written: one bad file (or an existing store) refuses
    the whole import with one error line (exit 2), and nothing is written.
    """
    from mpi_lidar.scans.importers import find_scan_files, import_files, plan_import
    from mpi_lidar.scans.importers.base import check_frequencies_in_hz

    freqs = None
    if frequencies:
        try:
            freqs = tuple(float(f) for f in frequencies.split(","))
        except ValueError:
            raise MpiLidarError(f"--frequencies must be comma-separated numbers in Hz, got {frequencies!r}") from None
        check_frequencies_in_hz(freqs, "--frequencies")  # before any file is read
    mapping = {}
    for item in variables:
        name, sep, variable = item.partition("=")
        if not sep or not name.strip() or not variable.strip():
            raise MpiLidarError(f"--var must be NAME=VARIABLE (e.g. depth=range_m), got {item!r}")
        if name.strip() in mapping:
            raise MpiLidarError(f"--var maps {name.strip()!r} twice")
        mapping[name.strip()] = variable.strip()
    plan = plan_import(find_scan_files(sources), out)

    def echo(scan, target: Path) -> None:
        click.echo(f"scan {scan.name}: {scan.shape[0]} x {scan.shape[1]} pixels at {len(scan.frequencies_hz)} "
                   f"frequencies written to {target}")

    import_files(plan, freqs, mapping, on_scan=echo, depth_wrapped=depths == "wrapped")


@cli.command("render-scenes")
@click.option("--out", "out_dir", type=click.Path(path_type=Path), required=True, help="Directory for the scans.")
@click.option("--scene", "names", multiple=True, help="Scene name (repeatable); default: the demo scenes.")
@click.option("--seed", type=int, default=0, show_default=True)
def render_scenes_command(out_dir: Path, names: tuple[str, ...], seed: int) -> None:
    """Render simulated scenes (cornered board, multi-object, flat wall, ...) as scan stores with references.

    \b
    Example:
      mpi-lidar render-scenes --out scenes --scene corner --scene flat_wall
    """
    from mpi_lidar.simulation.scenes import DEMO_SCENES, SCENES, render_scenes

    unknown = sorted(set(names) - set(SCENES))
    if unknown:
        raise MpiLidarError(f"unknown scene {unknown[0]!r}; choose from {', '.join(SCENES)}")
    for path in render_scenes(out_dir, names or DEMO_SCENES, seed=seed):
        click.echo(f"wrote {path}")


@cli.command()
@click.option("--data", type=click.Path(path_type=Path), required=True, help="Dataset store (.zarr).")
@click.option("--out", "--report", "report_dir", type=click.Path(path_type=Path), required=True,
              help="Report directory (--report is the older name).")
@click.option("--model", "model_dir", type=click.Path(path_type=Path), help="XGBoost model directory for its row.")
@click.option("--trials", type=click.IntRange(min=1), default=10, show_default=True, help="TPE trials per baseline.")
@click.option("--train-rows", type=click.IntRange(min=10), default=100_000, show_default=True,
              help="Train rows the scikit-learn baselines fit on.")
@click.option("--svm-rows", type=click.IntRange(min=10), default=20_000, show_default=True)
def table2(data: Path, report_dir: Path, model_dir: Path | None, trials: int, train_rows: int, svm_rows: int) -> None:
    """The paper's Table II: KNN, RF, SVM, DNN and XGBoost against raw and weighted depth.

    \b
    Example:
      mpi-lidar table2 --data runs/paper/dataset.zarr --model runs/paper/model --out runs/table2
    """
    from mpi_lidar.learning.baselines import table2 as make_table2
    from mpi_lidar.reporting.report import write_report
    from mpi_lidar.reporting.table2 import table2_report, table2_table

    with Display() as display, display.step("baselines", 4) as advance:
        result = make_table2(data, model_dir, train_rows=train_rows, trials=trials, svm_rows=svm_rows,
                             on_row=lambda _row: advance())
    report, figures = table2_report(result)
    write_report(report, report_dir, figures)
    table = table2_table(result)
    print_table(table.headers, table.rows)
    click.echo(f"report written to {report_dir}")


@cli.command()
@click.option("--out", "out_dir", type=click.Path(path_type=Path), required=True, help="Report directory.")
@click.option("--rows", type=click.IntRange(min=100), help="Train rows (default 50,000; the test set is half).")
@click.option("--quick", is_flag=True, help="Tiny sizes (seconds), for a first look and for tests.")
@click.option("--seed", type=click.IntRange(min=0), help="Seed of the simulated rows (default: the config's).")
def bench(out_dir: Path, rows: int | None, quick: bool, seed: int | None) -> None:
    """Run time against error: test MAE, training time and throughput of every estimator, Pareto fronts.

    \b
    Example:
      mpi-lidar bench --out runs/bench --quick
    """
    import dataclasses
    import os
    import platform

    from mpi_lidar.config import Config
    from mpi_lidar.workflows.bench import BenchPlan, run_bench, tradeoff_table, write_bench

    plan = BenchPlan.quick() if quick else BenchPlan()
    if rows is not None:
        plan = dataclasses.replace(plan, rows=rows, test_rows=max(10, rows // 2))
    config = Config() if seed is None else Config().replace(dataset={"seed": seed})
    with Display() as display, display.step("bench") as advance:
        result = run_bench(plan, config, on_step=advance)
    machine = f"Machine: {platform.machine()}, {os.cpu_count()} cores, Python {platform.python_version()}. "
    write_bench(result, out_dir, machine)
    table = tradeoff_table(result)
    print_table(table.headers, table.rows)
    click.echo(f"report written to {out_dir} ({result.wall_s:.0f} s)")


@cli.command()
@click.argument("stores", nargs=-1, required=True, type=click.Path(path_type=Path))
def verify(stores: tuple[Path, ...]) -> None:
    """Check datasets, scans and corrected outputs chunk by chunk against the fingerprints written with them.

    Prints one line per store; exits 1 if any store is damaged (a deleted, truncated or replaced chunk),
    naming the array and chunk.

    \b
    Example:
      mpi-lidar verify runs/quick/dataset.zarr runs/quick/scenes/*.scan.zarr runs/quick/corrected/*
    """
    from mpi_lidar.workflows.verify import verify_store

    damaged = 0
    for store in stores:
        try:
            result = verify_store(store)
        except MpiLidarError as exc:
            damaged += 1
            click.echo(f"error: {redact(str(exc))}", err=True)
            continue
        click.echo(f"ok {result.path}: {result.kind}, {result.chunks:,} chunks")
    if damaged:
        sys.exit(EXIT_FAILURE)


def main() -> None:
    """Run the command line; every error is one line on stderr.

    A user error (bad input, a damaged store, an unreachable service, a mistyped option) exits 2; anything
    unexpected exits 1 with its traceback written to a log file (printed with ``--debug``). Secrets are masked in
    every line. Without ``--debug`` nothing else reaches stderr (:func:`_quiet`).
    """
    install_log_redaction()  # every log line of every library, masked as the error lines are
    debug = "--debug" in sys.argv[1:]
    if debug:
        sys.argv.remove("--debug")
    inherited = os.environ.get("PYTHONWARNINGS")
    try:
        if not debug:
            _quiet()
        _run(debug)
    finally:  # this process's environment as it was (the command line called from Python, as in tests)
        if inherited is None:
            os.environ.pop("PYTHONWARNINGS", None)
        else:
            os.environ["PYTHONWARNINGS"] = inherited


def _run(debug: bool) -> None:
    """The command of ``sys.argv``; every error one line on stderr and its exit code (:func:`main`)."""
    try:
        cli.main(standalone_mode=False, prog_name="mpi-lidar")
    except click.ClickException as exc:
        click.echo(f"error: {redact(_usage_line(exc))}", err=True)
        sys.exit(EXIT_USER_ERROR)
    except (click.Abort, KeyboardInterrupt):
        click.echo("aborted", err=True)
        sys.exit(130)
    except MpiLidarError as exc:
        click.echo(f"error: {redact(str(exc))}", err=True)
        if debug:
            traceback.print_exc()
        sys.exit(EXIT_USER_ERROR)
    except Exception as exc:  # a bug or an environment problem: one line, the traceback in a file
        fault = environment_fault(exc)  # a full disk, a quota, a read-only file system: the user's to fix
        if fault is not None:
            click.echo(f"error: {redact(str(fault))}", err=True)
            if debug:
                click.echo(redact(traceback.format_exc()), err=True)
            sys.exit(EXIT_USER_ERROR)
        log = _write_traceback()
        reason = redact(str(exc).strip().splitlines()[0]) if str(exc).strip() else ""
        click.echo(f"error: unexpected {type(exc).__name__}: {reason} (traceback in {log}; rerun with --debug "
                   "to print it)", err=True)
        if debug:
            click.echo(redact(traceback.format_exc()), err=True)
        sys.exit(EXIT_FAILURE)


def _usage_line(exc: click.ClickException) -> str:
    """A usage error as one line: what is wrong and which ``--help`` lists the choices (Click's own message is
    three lines: usage, a hint and the error)."""
    if isinstance(exc, click.NoSuchOption):
        message = f"no such option {exc.option_name}"
        if exc.possibilities:
            message += f"; did you mean {' or '.join(sorted(exc.possibilities))}?"
    else:
        message = " ".join(exc.format_message().split())
        message = message[:1].lower() + message[1:]
    if not isinstance(exc, click.UsageError):
        return message
    ctx = exc.ctx
    if ctx is not None and not isinstance(ctx.command, click.Group):
        where = f"{ctx.command_path} --help lists the options"
    else:  # the group's own error (a mistyped command), or one raised before a command's context existed
        command = next((arg for arg in sys.argv[1:] if arg in cli.commands), None)
        where = (f"mpi-lidar {command} --help lists the options" if command and ctx is None
                 else "mpi-lidar --help lists the commands")
    return message.rstrip(".") + f" ({where})"


def _quiet() -> None:
    """Keep stderr for error lines, in this process and in the Dask worker processes it starts.

    numpy's RuntimeWarnings (an infinite depth, an overflow in a pixel's arithmetic) concern pixels that the
    validity stage flags and leaves out; they say nothing a user can act on. asyncio's and tornado's ERROR lines
    ("Task was destroyed but it is pending!") come from Dask's event loop being torn down after an error that
    has been reported already. Errors themselves are never silenced: they are exceptions, and each becomes one
    ``error:`` line. ``--debug`` shows everything.
    """
    import logging
    import warnings

    warnings.filterwarnings("ignore", category=RuntimeWarning)
    inherited = os.environ.get("PYTHONWARNINGS")  # for the worker processes this command starts
    os.environ["PYTHONWARNINGS"] = ",".join(filter(None, (inherited, "ignore::RuntimeWarning")))
    for name in ("asyncio", "tornado"):
        logging.getLogger(name).setLevel(logging.CRITICAL)


def _write_traceback() -> Path | str:
    """The current exception's traceback, secrets masked, in this user's private log file; its path."""
    return write_error_log(redact(traceback.format_exc())) or "no log: the temporary folder cannot be written"


if __name__ == "__main__":
    main()
