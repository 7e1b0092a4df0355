"""Prefect flow: generate a labelled dataset, one task per incomplete chunk on a Dask cluster.

The library does the work: :func:`mpi_lidar.workflows.generate.generate` runs the chunk loop (the same as
``mpi-lidar simulate``) on a :class:`flows.runtime.PrefectExecutor`, so each chunk is a run of
:data:`write_chunk_task`; :mod:`mpi_lidar.reporting.report` makes the summary. This flow only adds the tasks,
their retries and the artifact. A chunk task that fails is retried twice by Prefect after a short delay;
chunks already complete are skipped, so a re-run resumes a store. A complete store starts no cluster.
"""

from __future__ import annotations

from pathlib import Path

from prefect import flow, task
from prefect.artifacts import create_markdown_artifact
from prefect.cache_policies import NO_CACHE
from prefect.runtime import flow_run

from flows.runtime import PrefectExecutor, dask_task_runner, describe_workers, shared_api
from mpi_lidar.calibration.profile import read_profile
from mpi_lidar.config import Config, config_sha256, resolve_config, validate_overrides
from mpi_lidar.reporting import report
from mpi_lidar.simulation import dataset
from mpi_lidar.workflows.generate import CHUNK_RETRIES, GenerationReport, generate
from mpi_lidar.workflows.job_options import Workers

SUMMARY_ARTIFACT_KEY = "dataset-summary"
CHUNK_RETRY_DELAY_S = 2


def histogram_path(out: str | Path) -> Path:
    """``runs/x/dataset.zarr`` -> ``runs/x/dataset.error_hist.png``, beside the store."""
    out = Path(out)
    return out.with_name(f"{out.name.removesuffix('.zarr')}.error_hist.png")


def for_sensor(config: Config, sensor: str | None) -> Config:
    """The configuration with a sensor profile's frequencies, noise scale and working range (none: as it is),
    as ``mpi-lidar simulate --sensor`` and ``mpi-lidar pipeline --sensor`` apply it."""
    if sensor is None:
        return config
    return validate_overrides(read_profile(sensor).simulation(), config, source=f"sensor profile {sensor}")


@task(name="build-config", cache_policy=NO_CACHE)
def build_config_task(preset: str, config_file: str | None, samples: int | None, seed: int | None,
                      chunk_rows: int | None = None, fidelity: str | None = None, sensor: str | None = None) -> Config:
    """Preset, then the TOML file, then the options, then the sensor profile: the same precedence as the CLI."""
    config = resolve_config(config_file, preset, samples=samples, chunk_rows=chunk_rows, seed=seed, fidelity=fidelity)
    return for_sensor(config, sensor)


@task(name="create-store", cache_policy=NO_CACHE)
def create_store_task(out: str, config: Config) -> list[int]:
    """Create the store (or reopen one of the same config) and list the chunks still to write."""
    group = dataset.create_store(out, config)
    return dataset.incomplete_chunks(group)


# One chunk: the library's write_chunk itself, as a task run named after its chunk, retried by Prefect.
write_chunk_task = task(dataset.write_chunk, name="write-chunk", task_run_name="write-chunk-{index}",
                        cache_policy=NO_CACHE, retries=CHUNK_RETRIES, retry_delay_seconds=CHUNK_RETRY_DELAY_S)


@task(name="summarize", cache_policy=NO_CACHE)
def summarize_task(out: str) -> dataset.DatasetSummary:
    """Raw errors per frequency of the whole store, also when this run wrote nothing."""
    return dataset.summarize(out)


@task(name="error-histogram", cache_policy=NO_CACHE)
def histogram_task(out: str, png: str) -> str:
    """The paper's Fig. 5 for this store, as a PNG beside it."""
    return str(report.depth_error_histogram(out, png))


@task(name="publish-summary", cache_policy=NO_CACHE)
def publish_summary_task(summary: dataset.DatasetSummary, run: GenerationReport, workers: str) -> str:
    """The generation summary as a markdown artifact, under a key that keeps its history across runs."""
    markdown = report.generation_markdown(summary, run, workers)
    create_markdown_artifact(markdown=markdown, key=SUMMARY_ARTIFACT_KEY,
                             description=f"Dataset generation summary of {summary.path}")
    return markdown


@flow(name="generate-dataset")
def generate_dataset_flow(
    out: str,
    preset: str = "quick",
    config_file: str | None = None,
    samples: int | None = None,
    seed: int | None = None,
    workers: Workers = 2,
    scheduler: str | None = None,
    chunk_rows: int | None = None,
    fidelity: str | None = None,
    sensor: str | None = None,
) -> dict[str, object]:
    """Generate (or resume) the dataset store ``out``; publish its raw-error summary and histogram.

    The options are those of ``mpi-lidar simulate`` (``config_file`` is ``--config``, ``sensor`` a sensor
    profile whose sensor is simulated): ``workers`` processes of a LocalCluster simulate the chunks, or the
    Dask cluster at ``scheduler`` (``tcp://host:8786``); ``workers=0`` runs them in the flow's process. A
    complete store is only summarised again: no cluster is started.
    """
    config = build_config_task(preset, config_file, samples, seed, chunk_rows, fidelity, sensor)
    todo = create_store_task(out, config)
    runner = dask_task_runner(workers, scheduler) if todo and workers > 0 else None
    with shared_api(), PrefectExecutor(runner, [write_chunk_task]) as executor:
        run = generate(out, config, executor)
    summary = summarize_task(out)
    png = histogram_task(out, str(histogram_path(out)))
    publish_summary_task(summary, run, describe_workers(workers, scheduler))
    return {
        "path": out,
        "config_sha256": config_sha256(config),
        "chunks_written": run.chunks_written,
        "chunks_skipped": run.chunks_skipped,
        "rows_written": run.rows_written,
        "wall_s": run.wall_s,
        "rows_per_s": run.rows_per_s,
        "png": png,
        "flow_run_id": str(flow_run.id),
    }
