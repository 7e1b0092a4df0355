"""Prefect flow: correct an archive of scans, one task per scan on a Dask cluster.

The library does the work (:func:`mpi_lidar.workflows.correct_archive.process_scan` reads, corrects and
writes one scan's
outputs atomically, and turns a bad scan into a 'failed' outcome with its reason); this flow makes each scan
a task, writes the batch summary, and publishes it and every scan's metrics as artifacts. A scan already
corrected with the same model and options is skipped. The flow ends Failed when any scan failed, after all
the others were corrected and the summary was written, so nothing is lost and nothing failed silently.
"""

from __future__ import annotations

import time

from prefect import flow, task
from prefect.artifacts import create_markdown_artifact
from prefect.cache_policies import NO_CACHE
from prefect.runtime import flow_run

from flows.runtime import dask_task_runner, shared_api
from mpi_lidar.correction import CorrectionOptions, ScanOutcome
from mpi_lidar.errors import MpiLidarError
from mpi_lidar.learning.model import load_model
from mpi_lidar.reporting.scan_report import batch_report, write_batch_report
from mpi_lidar.workflows.correct_archive import expand_archive, process_scan

SUMMARY_ARTIFACT_KEY = "correction-summary"


@task(name="list-scans", cache_policy=NO_CACHE)
def list_scans_task(scans: list[str], model: str) -> list[str]:
    """The scan stores to correct; a model that cannot be loaded stops the batch before any work."""
    load_model(model)
    return expand_archive(scans)


@task(name="correct-scan", task_run_name="correct-{source}", cache_policy=NO_CACHE, retries=1,
      retry_delay_seconds=2)
def correct_scan_task(source: str, model: str, out: str, options: CorrectionOptions) -> ScanOutcome:
    """One scan: validity mask, gate, inference, outputs. Retried once for infrastructure failures only."""
    return process_scan(source, model, out, options)


@task(name="publish-scan", cache_policy=NO_CACHE)
def publish_scan_task(outcome: ScanOutcome) -> None:
    """One scan's outcome, metrics and output files as a markdown artifact."""
    lines = [f"Scan `{outcome.source}`: **{outcome.status}** {outcome.reason}".rstrip(), ""]
    for region, m in outcome.metrics.items():
        lines.append(f"- {region}: MAE {1e3 * m['raw_mae_m']:.3f} -> {1e3 * m['corrected_mae_m']:.3f} mm "
                     f"over {m['pixels']:,} pixels")
    if outcome.output:
        lines.append(f"- outputs: `{outcome.output}/` (report.html, maps.png, error_hist.png, point_cloud.png)")
    create_markdown_artifact(markdown="\n".join(lines), description=f"Correction of {outcome.name}")


@task(name="write-summary", cache_policy=NO_CACHE)
def summary_task(outcomes: list[ScanOutcome], wall_s: float, out: str) -> str:
    """The batch table as files and as an artifact under a key that keeps its history."""
    write_batch_report(outcomes, wall_s, out)
    markdown = batch_report(outcomes, wall_s).markdown()
    create_markdown_artifact(markdown=markdown, key=SUMMARY_ARTIFACT_KEY, description=f"Batch correction into {out}")
    return markdown


@flow(name="correct-archive")
def correct_archive_flow(scans: list[str], model: str, out: str, gate: str = "geometry", workers: int = 2,
                         scheduler: str | None = None) -> dict[str, object]:
    """Correct every scan of ``scans`` (stores, directories or globs) with ``model`` into ``out``."""
    options = CorrectionOptions(gate=gate)
    sources = list_scans_task(scans, model)
    started = time.perf_counter()
    with shared_api(), dask_task_runner(workers, scheduler) as runner:
        futures = [runner.submit(correct_scan_task, {"source": s, "model": model, "out": out, "options": options})
                   for s in sources]
        outcomes = sorted((f.result() for f in futures), key=lambda o: o.source)
    wall_s = time.perf_counter() - started
    for outcome in outcomes:
        publish_scan_task(outcome)
    summary_task(outcomes, wall_s, out)
    failed = [o for o in outcomes if o.status == "failed"]
    result = {"flow_run_id": str(flow_run.id), "wall_s": wall_s,
              "statuses": {o.source: o.status for o in outcomes}}
    if failed:
        reasons = "; ".join(f"{o.source}: {o.reason}" for o in failed)
        raise MpiLidarError(f"{len(failed)} of {len(outcomes)} scans failed ({reasons})")
    return result
