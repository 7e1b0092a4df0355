"""Prefect flow: generate a labelled dataset, one task per incomplete chunk on a Dask cluster.

The library does the work (:mod:`mpi_lidar.simulation.dataset`, :mod:`mpi_lidar.reporting.report`); this
flow only makes each step a task so that runs, retries and the summary are visible in Prefect. A
chunk task that fails is retried twice by Prefect after a short delay; chunks already complete are
skipped, so a re-run resumes a store.
"""

from __future__ import annotations

import time
from pathlib import Path

from prefect import flow, task
from prefect.artifacts import create_markdown_artifact
from prefect.cache_policies import NO_CACHE
from prefect.runtime import flow_run
from prefect_dask import DaskTaskRunner

from flows.runtime import dask_task_runner, describe_workers, shared_api
from mpi_lidar.config import Config, config_sha256, resolve_config
from mpi_lidar.reporting import report
from mpi_lidar.simulation import dataset

SUMMARY_ARTIFACT_KEY = "dataset-summary"
CHUNK_RETRIES = 2
CHUNK_RETRY_DELAY_S = 2


def histogram_path(out: str | Path) -> Path:
    """``runs/x/dataset.zarr`` -> ``runs/x/dataset.error_hist.png``, beside the store."""
    out = Path(out)
    return out.with_name(f"{out.name.removesuffix('.zarr')}.error_hist.png")


@task(name="build-config", cache_policy=NO_CACHE)
def build_config_task(preset: str, config_file: str | None, samples: int | None, seed: int | None) -> Config:
    """Preset, then the TOML file, then samples/seed: the same precedence as the CLI."""
    return resolve_config(config_file, preset, samples=samples, seed=seed)


@task(name="create-store", cache_policy=NO_CACHE)
def create_store_task(out: str, config: Config) -> list[int]:
    """Create the store (or reopen one of the same config) and list the chunks still to write."""
    group = dataset.create_store(out, config)
    return dataset.incomplete_chunks(group)


@task(name="write-chunk", task_run_name="write-chunk-{index}", cache_policy=NO_CACHE,
      retries=CHUNK_RETRIES, retry_delay_seconds=CHUNK_RETRY_DELAY_S)
def write_chunk_task(path: str, config: Config, index: int) -> bool:
    """Simulate one chunk into its rows of the store; False when it was already complete."""
    return dataset.write_chunk(path, config, index)


@task(name="summarize", cache_policy=NO_CACHE)
def summarize_task(out: str) -> dataset.DatasetSummary:
    """Raw errors per frequency of the whole store, also when this run wrote nothing."""
    return dataset.summarize(out)


@task(name="error-histogram", cache_policy=NO_CACHE)
def histogram_task(out: str, png: str) -> str:
    """The paper's Fig. 5 for this store, as a PNG beside it."""
    return str(report.depth_error_histogram(out, png))


@task(name="publish-summary", cache_policy=NO_CACHE)
def publish_summary_task(summary: dataset.DatasetSummary, run: dataset.GenerationReport, workers: str) -> str:
    """The generation summary as a markdown artifact, under a key that keeps its history across runs."""
    markdown = report.generation_markdown(summary, run, workers)
    create_markdown_artifact(markdown=markdown, key=SUMMARY_ARTIFACT_KEY,
                             description=f"Dataset generation summary of {summary.path}")
    return markdown


def write_chunks(runner: DaskTaskRunner, out: str, config: Config, todo: list[int]) -> tuple[list[int], float]:
    """Run one chunk task per index on the cluster; the chunks written and the seconds spent writing.

    The cluster is started before the clock, so the time (and the throughput) is that of the simulation,
    as in :func:`mpi_lidar.simulation.dataset.generate`, not of spawning workers.
    """
    with runner:
        _ = runner.client  # start the cluster (or connect to the scheduler) now
        started = time.perf_counter()
        futures = {i: runner.submit(write_chunk_task, {"path": out, "config": config, "index": i}) for i in todo}
        written = [i for i, future in futures.items() if future.result()]
        return written, time.perf_counter() - started


@flow(name="generate-dataset")
def generate_dataset_flow(
    out: str,
    preset: str = "quick",
    config_file: str | None = None,
    samples: int | None = None,
    seed: int | None = None,
    workers: int = 2,
    scheduler: str | None = None,
) -> dict[str, object]:
    """Generate (or resume) the dataset store ``out``; publish its raw-error summary and histogram.

    ``workers`` processes of a LocalCluster simulate the chunks, or the Dask cluster at ``scheduler``
    (``tcp://host:8786``). A complete store is only summarised again: no cluster is started.
    """
    config = build_config_task(preset, config_file, samples, seed)
    plan = dataset.SamplingPlan.from_config(config)
    started = time.perf_counter()
    todo = create_store_task(out, config)
    store_s = time.perf_counter() - started
    written, chunks_s = [], 0.0
    if todo:
        with shared_api():
            written, chunks_s = write_chunks(dask_task_runner(workers, scheduler), out, config, todo)
    run = dataset.GenerationReport(len(written), plan.chunks - len(written), plan.rows_in(written), store_s + chunks_s)
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
