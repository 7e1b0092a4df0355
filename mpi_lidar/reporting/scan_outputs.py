"""One corrected scan's outputs at an output level, written into a staging directory and swapped in at the end."""

from __future__ import annotations

import json
import time
from collections.abc import Callable, Iterator
from concurrent.futures import Future, ThreadPoolExecutor
from contextlib import contextmanager
from pathlib import Path
from typing import TYPE_CHECKING, TypeVar

import numpy as np

from mpi_lidar.correction import Correction, CorrectionOptions
from mpi_lidar.correction.corrected_store import write_corrected_store
from mpi_lidar.reporting.correction_notes import correction_notes
from mpi_lidar.reporting.metrics import measured_depth, metric_regions
from mpi_lidar.reporting.output_levels import OutputLevel, check_outputs
from mpi_lidar.reporting.point_cloud_files import point_cloud_formats, write_point_clouds
from mpi_lidar.reporting.report import REPORT_MARKER, Embed, error_histogram_figure, save_figure
from mpi_lidar.reporting.scan_report import scan_report
from mpi_lidar.reporting.thumbnail import azimuth_rises, thumbnail_image, thumbnail_legend, with_key, write_png
from mpi_lidar.scans import geometry
from mpi_lidar.scans.pointcloud import PointCloudFormat
from mpi_lidar.scans.scan import Scan
from mpi_lidar.storage.atomic import atomic_path

if TYPE_CHECKING:
    from matplotlib.figure import Figure

T = TypeVar("T")


def write_scan_outputs(target: Path, scan: Scan, correction: Correction,
                       metrics: dict[str, dict[str, float]] | Future[dict[str, dict[str, float]]],
                       identity: dict[str, str], options: CorrectionOptions, outputs: str = "full",
                       cpu_s: dict[str, float] | None = None,
                       point_clouds: tuple[str, ...] | list[str] | None = None,
                       bundle_dir: Path | None = None, point_cloud_frame: str = "scanner",
                       no_return_range_m: float | None = None) -> list[str]:
    """One scan's outputs at level ``outputs``, written into a staging directory and swapped in at the end.

    ``data``: ``corrected.zarr`` and ``metrics.json`` (counts, metrics, notes, the outputs written); ``light``:
    those, ``report.md``/``report.html``, ``corrected.laz`` and ``thumbnail.png`` (corrected depth and flags, at
    most :data:`~mpi_lidar.reporting.thumbnail.THUMBNAIL_PX` pixels wide); ``full``: those, plus the
    maps, the error histogram, the point-cloud views, an interactive 3-D view in report.html (linking one shared
    ``plotly.min.js`` in ``bundle_dir``, by default the folder holding ``target``: one per batch) and the point
    clouds. ``point_clouds``: the formats written at any level
    (:data:`~mpi_lidar.reporting.point_cloud_files.POINT_CLOUD_FILES`: ``ply`` writes ``raw.ply`` and
    ``corrected.ply``, ``las``/``laz`` ``corrected.las``/``.laz``, every file with the named fields of
    :func:`mpi_lidar.scans.pointcloud.correction_fields`, and the uncertainty where the correction has one;
    :func:`~mpi_lidar.reporting.point_cloud_files.write_point_clouds` says what each holds); None: ``ply`` and
    ``laz`` at level full, ``laz`` at light, none at data; ``point_cloud_frame`` and ``no_return_range_m`` where
    their points lie (:func:`~mpi_lidar.reporting.point_cloud_files.write_point_clouds`). ``metrics`` are
    :func:`~mpi_lidar.reporting.metrics.scan_metrics`, or a future of them (the store is written while they are
    worked out). Returns the notes for the batch summary;
    ``cpu_s``, if given, gets the CPU seconds of this process spent on ``write`` (store, point clouds, report, and a
    future's metrics) and ``figures`` (drawing and encoding PNGs, the 3-D view). Nothing of pyplot's global state is
    touched: the figures are drawn on figures of their own.
    """
    level = check_outputs(outputs)
    if level == OutputLevel.FULL:  # matplotlib and plotly are imported where the full level draws with them
        from mpi_lidar.reporting.cloud_figures import (
            VIEW_3D_FALLBACK,
            plotly_js_src,
            point_cloud_figure,
            point_cloud_view_3d,
            write_plotly_js,
        )
        from mpi_lidar.reporting.figures import maps_figure
    formats = point_cloud_formats(outputs, point_clouds)
    cpu_s = {} if cpu_s is None else cpu_s
    notes: list[str] = list(correction_notes(correction))
    if scan.reference_depth is None:
        notes.append("no reference depth: errors, error maps and histogram skipped")
    with atomic_path(target, replace=True, what="scan outputs") as staging, ThreadPoolExecutor(1) as beside:
        staging.mkdir()
        # The thumbnail needs nothing of the store: it is drawn on a thread beside the store's writing.
        thumbnail = (beside.submit(_thread_cpu, _write_thumbnail, staging, correction, azimuth_rises(scan))
                     if level != OutputLevel.DATA else None)
        started = time.process_time()
        write_corrected_store(staging / "corrected.zarr", scan, correction, identity, options, outputs)
        depth_limits, thumbnail_cpu = thumbnail.result() if thumbnail is not None else (None, 0.0)
        if isinstance(metrics, Future):
            metrics = metrics.result()
        cpu_s["figures"] = cpu_s.get("figures", 0.0) + thumbnail_cpu
        cpu_s["write"] = cpu_s.get("write", 0.0) + time.process_time() - started - thumbnail_cpu
        figures: dict[str, Figure] = {}
        files = ["corrected.zarr"]
        embeds: list[Embed] = []
        if level == OutputLevel.FULL:
            with _cpu(cpu_s, "figures"):
                figures["maps.png"] = maps_figure(scan, correction)
                where = metric_regions(scan, correction).get("whole map")
                if scan.reference_depth is not None and where is not None and where.any():
                    figures["error_hist.png"] = error_histogram_figure(
                        {f"raw {scan.frequencies_hz[-1] / 1e6:g} MHz":
                         1e3 * (measured_depth(scan, correction) - scan.reference_depth)[where],
                         "corrected": 1e3 * (correction.depth - scan.reference_depth)[where]}, "depth error [mm]",
                        "pixels (count)")
        # Whole rays where level full draws its views or PLY files are written; LAS and LAZ take a band at a time.
        whole = level == OutputLevel.FULL or PointCloudFormat.PLY in formats
        rays = scan.rays() if whole else None
        cloud_rays = rays if rays is not None else scan.ray_rows() if formats else None
        if cloud_rays is not None:
            measured = measured_depth(scan, correction)
            with _cpu(cpu_s, "write"):
                files += write_point_clouds(staging, formats, cloud_rays, scan, correction, frame=point_cloud_frame,
                                            no_return_range_m=no_return_range_m)
            # Views of no point would be empty axes: a scan without a corrected depth has its maps only.
            if level == OutputLevel.FULL and rays is not None and np.isfinite(correction.depth).any():
                with _cpu(cpu_s, "figures"):
                    raw_points = geometry.point_cloud(np.where(np.isfinite(correction.depth), measured, np.nan), rays)
                    corrected_points = geometry.point_cloud(correction.depth, rays)
                    figures["point_cloud.png"] = point_cloud_figure(raw_points, corrected_points)
                    bundle = write_plotly_js(target.parent if bundle_dir is None else bundle_dir)
                    embeds.append(Embed(point_cloud_view_3d(raw_points, corrected_points,
                                                            1e3 * (correction.depth - measured)),
                                        fallback=VIEW_3D_FALLBACK, scripts=(plotly_js_src(bundle, target),)))
                    del raw_points, corrected_points
            del rays, cloud_rays
        elif level == OutputLevel.FULL:
            notes.append("no scan geometry: point clouds and views skipped")
        elif formats:
            notes.append("no scan geometry: point clouds skipped")
        if level == OutputLevel.FULL:
            with _cpu(cpu_s, "figures"):
                for name, fig in figures.items():
                    save_figure(fig, staging / name)
        images = (sorted([*figures, "thumbnail.png"]) if level == OutputLevel.FULL
                  else ["thumbnail.png"] if level == OutputLevel.LIGHT else [])
        files += images + ([] if level == OutputLevel.DATA else ["report.md", "report.html"]) + ["metrics.json"]
        with _cpu(cpu_s, "write"):
            captions = {"thumbnail.png": thumbnail_legend(depth_limits)} if depth_limits is not None else None
            report = scan_report(scan, correction, metrics, notes, images, outputs, files, captions, embeds)
            if level != OutputLevel.DATA:
                (staging / "report.md").write_text(report.markdown())
                (staging / "report.html").write_text(report.html())
            (staging / "metrics.json").write_text(json.dumps(report.data, indent=2, sort_keys=True) + "\n")
            (staging / REPORT_MARKER).write_text("")
    return notes


def _write_thumbnail(staging: Path, correction: Correction, mirror: bool = False) -> tuple[float, float]:
    """``thumbnail.png`` of the correction in ``staging`` (its columns right to left where ``mirror``); returns the
    depth limits of its colour scale [m]."""
    image, depth_limits = thumbnail_image(correction, mirror=mirror)
    write_png(staging / "thumbnail.png", with_key(image, correction.flags, depth_limits))
    return depth_limits


def _thread_cpu(work: Callable[..., T], *args: object) -> tuple[T, float]:
    """``work(*args)`` and the CPU seconds of this thread it took (a thread beside the caller's)."""
    started = time.thread_time()
    return work(*args), time.thread_time() - started


@contextmanager
def _cpu(seconds: dict[str, float], stage: str) -> Iterator[None]:
    started = time.process_time()
    try:
        yield
    finally:
        seconds[stage] = seconds.get(stage, 0.0) + time.process_time() - started
