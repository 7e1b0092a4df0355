"""Prefect flow: correct an archive of scans, one task per scan, in the flow's process or on a Dask cluster.

The library does the work: :func:`mpi_lidar.workflows.correct_archive.correct_archive`, the same call as
``mpi-lidar correct``, checks the model and the gate, removes the staging an interrupted run left, and runs
:func:`~mpi_lidar.workflows.correct_archive.process_scan` once per scan (it reads, corrects and writes one
scan's outputs atomically, and turns a bad scan into a 'failed' outcome with its reason) on a
:class:`flows.runtime.PrefectExecutor`, so each scan is a run of :data:`correct_scan_task`. This flow adds
the tasks, the batch summary and the artifacts of it and of every scan's metrics (each under a key:
:func:`artifact_slugs`). By default (``workers=0``, as ``mpi-lidar correct``) the scans run one after the
other in the flow's process, every core on each, and no Dask cluster is started. A scan already corrected
with the same model and options is skipped (its numbers read back from its outputs). The flow ends Failed
when any scan failed, is unserved (unless ``allow_unserved``), or has a status named in ``fail_on`` (degraded,
unchanged), after all the others were
corrected and the summary was written, so nothing is lost and nothing failed silently.
"""

from __future__ import annotations

import re
import time
from collections.abc import Iterable

from prefect import flow, task
from prefect.artifacts import create_link_artifact, create_markdown_artifact, create_table_artifact
from prefect.cache_policies import NO_CACHE
from prefect.runtime import flow_run

from flows.parameters import declared_parameters
from flows.runtime import PrefectExecutor, dask_task_runner, shared_api
from mpi_lidar.correction import CorrectionOptions, GateName, ScanOutcome
from mpi_lidar.correction.options import USER_OPTIONS, Baseline
from mpi_lidar.errors import MpiLidarError
from mpi_lidar.locations import location
from mpi_lidar.reporting.batch_report import batch_report
from mpi_lidar.reporting.output_levels import OutputLevel
from mpi_lidar.scans.pointcloud import PointCloudFormat, PointCloudFrame
from mpi_lidar.storage.objects import exists
from mpi_lidar.workflows.batch_options import BATCH_OPTIONS, BatchOptions, FailOn, batch_options
from mpi_lidar.workflows.correct_archive import batch_failure, correct_archive, process_scan
from mpi_lidar.workflows.remote_outputs import write_summary

TABLE_ARTIFACT_KEY = "correction-table"
SUMMARY_ARTIFACT_KEY = "correction-summary"

# One scan: the library's process_scan itself (validity mask, gate, inference, outputs), as a task run named
# after its source. A bad scan returns a 'failed' outcome, so the one retry is for infrastructure failures.
correct_scan_task = task(process_scan, name="correct-scan", task_run_name="correct-{source}",
                         cache_policy=NO_CACHE, retries=1, retry_delay_seconds=2)


def artifact_slugs(names: Iterable[str]) -> list[str]:
    """Each scan name as the tail of its Prefect artifact keys: lowercase letters, digits and dashes.

    Prefect keys allow nothing else, so ``Cornered_Board`` is ``cornered-board``; a name whose slug an
    earlier name of the batch already took gets ``-2``, ``-3`` in batch order (by source). A scan's keys,
    ``scan-<slug>`` (its outcome) and ``report-<slug>`` (the link to its report), keep the history of that
    scan's artifacts across runs.
    """
    slugs: list[str] = []
    for name in names:
        base = re.sub(r"[^a-z0-9]+", "-", name.lower()).strip("-") or "unnamed"
        slug, n = base, 1
        while slug in slugs:
            n += 1
            slug = f"{base}-{n}"
        slugs.append(slug)
    return slugs


@task(name="publish-scans", cache_policy=NO_CACHE)
def publish_scans_task(outcomes: list[ScanOutcome]) -> list[str]:
    """Every scan's artifacts, in one task run (a task run per scan would cost a batch more than its artifacts);
    returns their keys."""
    keys = []
    for outcome, slug in zip(outcomes, artifact_slugs(o.name for o in outcomes), strict=True):
        keys.extend(publish_scan(outcome, slug))
    return keys


def publish_scan(outcome: ScanOutcome, slug: str) -> list[str]:
    """One scan's outcome, metrics and output files as a markdown artifact (key ``scan-<slug>``) and a link to
    its report (key ``report-<slug>``); returns the keys."""
    lines = [f"Scan `{outcome.source}`: **{outcome.status}** {outcome.reason}".rstrip(), ""]
    for region, m in outcome.metrics.items():
        lines.append(f"- {region}: MAE {1e3 * m['raw_mae_m']:.3f} -> {1e3 * m['corrected_mae_m']:.3f} mm "
                     f"over {m['pixels']:,} pixels")
    if outcome.output:
        lines.append(f"- outputs: `{outcome.output}/` (its report lists them)")
    create_markdown_artifact(markdown="\n".join(lines), key=f"scan-{slug}",
                             description=f"Correction of {outcome.name}")
    link = _report_link(outcome.output) if outcome.output else None
    if link is not None:
        create_link_artifact(link=link, link_text=f"report of {outcome.name}", key=f"report-{slug}",
                             description=f"Correction report of {outcome.source}")
        return [f"scan-{slug}", f"report-{slug}"]
    return [f"scan-{slug}"]


def _report_link(output: str) -> str | None:
    """The address of a scan's report where it was written: a file URI on disk, the object's URL in a store."""
    report = location(output).joinpath("report.html")
    if report.is_local:
        path = report.local_path()
        return path.resolve().as_uri() if path.is_file() else None
    return report.url if exists(report) else None


@task(name="write-summary", cache_policy=NO_CACHE)
def summary_task(outcomes: list[ScanOutcome], wall_s: float, out: str) -> str:
    """The batch table as files and as an artifact under a key that keeps its history."""
    write_summary(outcomes, wall_s, out)  # on disk or published into the store
    markdown = batch_report(outcomes, wall_s).markdown()
    create_markdown_artifact(markdown=markdown, key=SUMMARY_ARTIFACT_KEY, description=f"Batch correction into {out}")
    create_table_artifact(table=batch_rows(outcomes), key=TABLE_ARTIFACT_KEY,
                          description=f"One row per scan of the batch into {out}")
    return markdown


def batch_rows(outcomes: list[ScanOutcome]) -> list[dict[str, object]]:
    """The batch as table rows: status, counts, the MAEs that exist [mm], seconds and source of every scan."""
    rows = []
    for o in outcomes:
        row: dict[str, object] = {"scan": o.name, "status": str(o.status), "source": o.source,
                                  "seconds": round(o.seconds, 3), **{f"{k} pixels": v for k, v in o.counts.items()}}
        for region, m in o.metrics.items():
            row[f"{region} raw MAE [mm]"] = round(1e3 * m["raw_mae_m"], 3)
            row[f"{region} corrected MAE [mm]"] = round(1e3 * m["corrected_mae_m"], 3)
        rows.append(row)
    return rows


def correct_and_publish(scans: list[str], model: str, out: str, options: CorrectionOptions, workers: int,
                        scheduler: str | None, outputs: str = "light",
                        point_clouds: tuple[str, ...] | None = None,
                        batch: BatchOptions | None = None) -> tuple[list[ScanOutcome], float]:
    """Inside a flow: correct the scans, publish each outcome and write and publish the batch summary.

    ``workers`` processes of a LocalCluster, or the Dask cluster at ``scheduler``, run the scans; with
    neither (``workers=0``) they run in the flow's process, as ``mpi-lidar correct --workers 0``. Returns
    the outcomes, by source, and the seconds the batch took. ``outputs``: each scan's output level;
    ``point_clouds``: the point-cloud formats each scan writes (None: the level's, laz at light, ply and laz at
    full, none at data); ``batch`` the rest of the batch's options (the point clouds' frame and no-return range,
    ``replace_options``). The summary counts every scan of ``out``, those earlier batches left there too.
    """
    batch = batch or BatchOptions()
    runner = dask_task_runner(workers, scheduler) if workers > 0 or scheduler else None
    started = time.perf_counter()
    summarised: list[ScanOutcome] = []
    with shared_api(), PrefectExecutor(runner, [correct_scan_task]) as executor:
        outcomes = correct_archive(scans, model, out, options, executor, outputs=outputs,
                                   point_clouds=point_clouds, on_done=summarised.extend,
                                   **batch.point_cloud_placement(), replace_options=batch.replace_options)
    wall_s = time.perf_counter() - started
    publish_scans_task(outcomes)
    summary_task(summarised or outcomes, wall_s, out)
    return outcomes, wall_s


class BatchFailedError(MpiLidarError):
    """A batch that fails (a scan failed, is unserved, or has a status of ``fail_on``), carrying the flow's result
    (:attr:`result`: each scan's status), so ``python -m flows`` still prints it."""

    def __init__(self, message: str, result: dict[str, object]) -> None:
        super().__init__(message)
        self.result = result

    def __reduce__(self) -> tuple[type[BatchFailedError], tuple[str, dict[str, object]]]:
        return (type(self), (str(self), self.result))


@flow(name="correct-archive")
@declared_parameters((CorrectionOptions, USER_OPTIONS), (BatchOptions, BATCH_OPTIONS))
def correct_archive_flow(scans: list[str], model: str, out: str, gate: GateName = GateName.GEOMETRY,
                         min_bias_mm: float | None = None, footprint_area_m2: float | str | None = None,
                         amplitude_scale: float | str | None = None, baseline: Baseline = Baseline.FUSED,
                         max_invalid_share: float | None = None, sensor: str | None = None,
                         fail_on: list[FailOn] | None = None, allow_unserved: bool = False,
                         outputs: OutputLevel = OutputLevel.LIGHT,
                         point_clouds: list[PointCloudFormat] | None = None,
                         point_cloud_frame: PointCloudFrame = PointCloudFrame.SCANNER,
                         no_return_range: float | None = None, replace_options: bool = False, workers: int = 0,
                         scheduler: str | None = None) -> dict[str, object]:
    """Correct every scan of ``scans`` with ``model`` into ``out``, as ``mpi-lidar correct`` does.

    Its options are this flow's parameters, by the same names (``--min-bias-mm`` is ``min_bias_mm``; None keeps
    the default, or the sensor profile's), checked as it checks them before any scan runs. With ``workers=0``
    the scans run in the flow's process, every core on each, and no Dask cluster is started. The flow ends
    Failed, after the summary is written, when a scan failed, is unserved (unless ``allow_unserved``) or has a
    status of ``fail_on`` (its error, a :class:`BatchFailedError`, carries the result). Returns the flow run's id, the
    wall time and each source's status. Point clouds: laz at light, ply and laz at full, none at data, unless
    ``point_clouds`` names the formats.

    Args:
        scans: Scan stores, directories or globs.
        model: Model directory.
        out: Output directory.
    """
    options, batch = batch_options(locals())  # the parameters, by name
    outcomes, wall_s = correct_and_publish(scans, model, out, options, batch.workers, batch.scheduler,
                                           batch.outputs.value, batch.point_cloud_formats(), batch)
    result: dict[str, object] = {"flow_run_id": str(flow_run.id), "wall_s": wall_s,
                                 "statuses": {o.source: str(o.status) for o in outcomes}}
    failure = batch_failure(outcomes, batch.fail_on, batch.allow_unserved)
    if failure:
        raise BatchFailedError(failure, result)
    return result
