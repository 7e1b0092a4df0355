"""Outputs of a corrected scan and of a batch: metrics, maps, histograms, point clouds, reports."""

from __future__ import annotations

import json
import os
import time
from collections.abc import Callable, Iterator
from concurrent.futures import Future, ThreadPoolExecutor
from contextlib import contextmanager
from pathlib import Path
from typing import TypeVar

import matplotlib
import matplotlib.image
import matplotlib.pyplot as plt
import numpy as np
import zarr
from matplotlib.colors import ListedColormap

from mpi_lidar.correction import (
    CORRECTED_SCHEMA,
    INVALID_FLAGS,
    Correction,
    CorrectionOptions,
    Flag,
    ScanOutcome,
    ScanStatus,
)
from mpi_lidar.correction.outcome import invalid_share
from mpi_lidar.errors import MpiLidarError
from mpi_lidar.reporting.report import (
    REPORT_MARKER,
    Embed,
    Report,
    Table,
    error_histogram_figure,
    save_figure,
    write_report,
)
from mpi_lidar.scans import geometry
from mpi_lidar.scans.scan import Scan, consolidate, store_fingerprints, write_described_arrays
from mpi_lidar.storage.atomic import atomic_path

T = TypeVar("T")
FLAG_COLOURS = ["#2e86de", "#c8d6e5", "#222f3e", "#576574", "#ee5253", "#ff9f43", "#10ac84", "#f6e58d", "#a55eea"]
GATED_OUT = ("not_needed", "no_multipath", "uncalibrated")


def _regions(scan: Scan, correction: Correction, rows: slice = slice(None)) -> dict[str, np.ndarray]:
    """Where the metrics are taken, per region, for a range of rows: pixels with a reference depth and a
    valid measurement (whole map), and those of them in the reference mask (masked region)."""
    if scan.reference_depth is None:
        return {}
    usable = np.isfinite(scan.reference_depth[rows]) & ~np.isin(correction.flags[rows],
                                                                [int(f) for f in INVALID_FLAGS])
    regions = {"whole map": usable}
    if scan.reference_mask is not None:
        regions["masked region"] = usable & scan.reference_mask[rows]
    return regions


def scan_metrics(scan: Scan, correction: Correction) -> dict[str, dict[str, float]]:
    """MAE, RMSE and max error of the raw highest-frequency depth and of the corrected depth, per region. [m]

    Summed a band of rows at a time (:data:`METRIC_BAND_PIXELS`), so a scan kept in its store is read one
    band at a time and the float64 errors of the whole scan never exist at once.
    """
    if scan.reference_depth is None:
        return {}
    h, w = scan.shape
    sums: dict[str, tuple[_ErrorSums, _ErrorSums]] = {}
    step = max(1, METRIC_BAND_PIXELS // max(w, 1))
    for top in range(0, h, step):
        rows = slice(top, min(top + step, h))
        reference = scan.reference_depth[rows]
        raw, corrected = scan.depth[-1, rows], correction.depth[rows]
        for region, where in _regions(scan, correction, rows).items():
            before, after = sums.setdefault(region, (_ErrorSums(), _ErrorSums()))
            before.add(raw[where], reference[where])
            after.add(corrected[where], reference[where])
    metrics = {}
    for region, (before, after) in sums.items():
        metrics[region] = {"pixels": before.rows, "raw_mae_m": before.mae_m(), "raw_rmse_m": before.rmse_m(),
                           "raw_max_abs_m": before.max_abs_m, "corrected_mae_m": after.mae_m(),
                           "corrected_rmse_m": after.rmse_m(), "corrected_max_abs_m": after.max_abs_m}
    return metrics


# Pixels per band of rows that :func:`scan_metrics` works on at once.
METRIC_BAND_PIXELS = 1 << 20


class _ErrorSums:
    """Running sums of the finite errors of estimates against a truth, band by band. [m]"""

    def __init__(self) -> None:
        self.rows, self.abs_sum, self.square_sum, self.max_abs_m = 0, 0.0, 0.0, float("nan")

    def add(self, estimate: np.ndarray, truth: np.ndarray) -> None:
        error = estimate.astype(np.float64)
        error -= truth
        error = np.abs(error[np.isfinite(error)])
        if error.size:
            self.rows += int(error.size)
            self.abs_sum += float(error.sum())
            self.square_sum += float(np.square(error).sum())
            self.max_abs_m = float(np.fmax(self.max_abs_m, error.max()))

    def mae_m(self) -> float:
        return self.abs_sum / self.rows if self.rows else float("nan")

    def rmse_m(self) -> float:
        return float(np.sqrt(self.square_sum / self.rows)) if self.rows else float("nan")


def applied_correction_mm(scan: Scan, correction: Correction) -> np.ndarray:
    """What correction did per pixel: corrected minus raw highest-frequency depth [mm], NaN where the pixel
    was not corrected (left as measured, or invalid)."""
    with np.errstate(invalid="ignore"):
        applied = 1e3 * (correction.depth.astype(np.float64) - scan.depth[-1])
    return np.where(correction.flags == Flag.CORRECTED, applied, np.nan)


def grid_axes(scan: Scan) -> tuple[tuple[float, float, float, float] | None, str, str]:
    """``extent`` of ``imshow`` and the axis labels of a map of the scan grid: azimuth and elevation [deg]
    where the scan has an azimuth/elevation grid, pixel indices otherwise (extent None)."""
    h, w = scan.shape
    az, el = scan.azimuth_rad, scan.elevation_rad
    if az is None or el is None or np.size(az) != w or np.size(el) != h:
        return None, "column [pixel]", "row [pixel]"
    az, el = np.degrees(np.asarray(az, dtype=np.float64)), np.degrees(np.asarray(el, dtype=np.float64))
    half_az = 0.5 * (az[-1] - az[0]) / (w - 1) if w > 1 else 0.05
    half_el = 0.5 * (el[-1] - el[0]) / (h - 1) if h > 1 else 0.05
    # imshow draws row 0 at the top: the top edge is the first row's elevation.
    extent = (float(az[0] - half_az), float(az[-1] + half_az), float(el[-1] + half_el), float(el[0] - half_el))
    return extent, "azimuth [deg]", "elevation [deg]"


def maps_figure(scan: Scan, correction: Correction) -> plt.Figure:
    """Raw and corrected depth, amplitude, what correction did and the flag map; with a reference depth also
    the error maps before and after (Fig. 7/8 b-f).

    Without a reference (every archived scan) the second row shows the applied correction (corrected minus
    raw depth, where corrected), the geometry gate's expected multipath bias and the flags; with one, the
    applied correction joins the first row and the error maps the second. Axes in degrees of azimuth and
    elevation where the scan has that grid, pixel indices otherwise.
    """
    reference = scan.reference_depth is not None
    columns = 4 if reference else 3
    fig, axes = plt.subplots(2, columns, figsize=(4.4 * columns, 7.5), squeeze=False)
    grid = grid_axes(scan)
    label = f"{scan.frequencies_hz[-1] / 1e6:g} MHz"
    finite = scan.depth[-1][np.isfinite(correction.depth)]
    limits = np.quantile(finite, [0.01, 0.99]) if finite.size else (0.0, 1.0)
    _image(axes[0, 0], scan.depth[-1], f"raw depth {label} [m]", "viridis", limits, grid)
    _image(axes[0, 1], correction.depth, "corrected depth [m]", "viridis", limits, grid)
    _image(axes[0, 2], scan.amplitude[-1], f"amplitude {label} [V$^2$]", "magma", None, grid)
    applied = applied_correction_mm(scan, correction)
    shown = np.abs(applied[np.isfinite(applied)])
    span = max(float(np.quantile(shown, 0.99)), 1e-3) if shown.size else 1.0
    _image(axes[0, 3] if reference else axes[1, 0], applied,
           f"applied correction [mm]\n({shown.size:,} pixels corrected)", "RdBu_r", (-span, span), grid)
    if reference:
        raw_error = 1e3 * (scan.depth[-1] - scan.reference_depth)
        corrected_error = 1e3 * (correction.depth - scan.reference_depth)
        valid = np.isfinite(corrected_error)
        span = float(np.quantile(np.abs(raw_error[valid]), 0.99)) if valid.any() else 1.0
        raw_error[~valid] = np.nan
        _image(axes[1, 0], raw_error, "raw error [mm]", "RdBu_r", (-span, span), grid)
        _image(axes[1, 1], corrected_error, "corrected error [mm]", "RdBu_r", (-span, span), grid)
    bias_ax = axes[1, 2] if reference else axes[1, 1]
    if correction.multipath_bias_m is not None:
        bias = 1e3 * np.asarray(correction.multipath_bias_m, dtype=np.float64)
        finite_bias = bias[np.isfinite(bias)]
        top = max(float(np.quantile(finite_bias, 0.99)), 1e-3) if finite_bias.size else 1.0
        _image(bias_ax, bias, "expected multipath bias [mm]", "cividis", (0.0, top), grid)
    else:
        bias_ax.text(0.5, 0.5, "expected multipath bias:\ncomputed by the geometry gate only", ha="center",
                     va="center")
        bias_ax.set_axis_off()
    flag_ax = axes[1, -1]
    flag_image = flag_ax.imshow(correction.flags, cmap=ListedColormap(FLAG_COLOURS), vmin=-0.5,
                                vmax=len(Flag) - 0.5, interpolation="nearest", extent=grid[0])
    bar = fig.colorbar(flag_image, ax=flag_ax, ticks=range(len(Flag)))
    bar.ax.set_yticklabels([f.name.lower().replace("_", " ") for f in Flag])
    flag_ax.set_title("what was done per pixel")
    flag_ax.set_xlabel(grid[1])
    flag_ax.set_ylabel(grid[2])
    fig.suptitle(f"scan {scan.name}")
    fig.tight_layout()
    return fig


def _image(ax: plt.Axes, values: np.ndarray, title: str, cmap: str, limits,
           grid: tuple[tuple[float, float, float, float] | None, str, str]) -> None:
    shown = ax.imshow(values, cmap=cmap, vmin=None if limits is None else limits[0],
                      vmax=None if limits is None else limits[1], interpolation="nearest", extent=grid[0])
    ax.figure.colorbar(shown, ax=ax)
    ax.set_title(title)
    ax.set_xlabel(grid[1])
    ax.set_ylabel(grid[2])


POINT_CLOUD_BINS = 400  # pixels per axis of a rasterized view: a million points cost what a thousand do


def point_cloud_figure(raw_points: np.ndarray, corrected_points: np.ndarray) -> plt.Figure:
    """Top and side views of the raw and corrected point clouds (Fig. 9), rasterized.

    Each view is a 2-D histogram of the points, coloured by the mean of the coordinate it hides, so drawing
    costs the same for a thousand points as for ten million, and both columns share their extents.
    """
    finite = [p.reshape(-1, 3)[np.isfinite(p.reshape(-1, 3)).all(axis=1)] for p in (raw_points, corrected_points)]
    views = (("top view", 0, 2, 1, "x [m]", "z (forward) [m]"), ("side view", 2, 1, 0, "z (forward) [m]", "y (up) [m]"))
    fig, axes = plt.subplots(2, 2, figsize=(11, 8), squeeze=False)
    for row, (title, u, v, colour, xlabel, ylabel) in enumerate(views):
        extent = _view_extent(finite, u, v)
        hidden = np.concatenate([c[:, colour] for c in finite])
        low, high = np.quantile(hidden, [0.01, 0.99]) if hidden.size else (0.0, 1.0)
        for column, (label, points) in enumerate(zip(("raw", "corrected"), finite, strict=True)):
            ax = axes[row, column]
            image = _mean_raster(points[:, u], points[:, v], points[:, colour], extent)
            shown = ax.imshow(image, origin="lower", extent=extent, cmap="viridis", interpolation="nearest",
                              aspect="equal", vmin=low, vmax=high)
            fig.colorbar(shown, ax=ax, label=f"{'xyz'[colour]} [m] (mean per cell)")
            ax.set_title(f"{label}: {title} ({points.shape[0]:,} points)")
            ax.set_xlabel(xlabel)
            ax.set_ylabel(ylabel)
    fig.tight_layout()
    return fig


def _view_extent(clouds: list[np.ndarray], u: int, v: int) -> tuple[float, float, float, float]:
    both = np.concatenate([c[:, [u, v]] for c in clouds]) if any(c.size for c in clouds) else np.zeros((1, 2))
    low, high = both.min(axis=0), both.max(axis=0)
    pad = np.maximum(1e-3, 0.02 * (high - low))
    return (float(low[0] - pad[0]), float(high[0] + pad[0]), float(low[1] - pad[1]), float(high[1] + pad[1]))


def _mean_raster(u: np.ndarray, v: np.ndarray, value: np.ndarray, extent: tuple[float, float, float, float],
                 bins: int = POINT_CLOUD_BINS) -> np.ndarray:
    """Mean of ``value`` per cell of a bins x bins grid over ``extent`` (rows along v); NaN where empty."""
    column = np.clip(((u - extent[0]) / (extent[1] - extent[0]) * bins).astype(np.int64), 0, bins - 1)
    row = np.clip(((v - extent[2]) / (extent[3] - extent[2]) * bins).astype(np.int64), 0, bins - 1)
    cell = row * bins + column
    count = np.bincount(cell, minlength=bins * bins)
    total = np.bincount(cell, weights=value, minlength=bins * bins)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(count > 0, total / count, np.nan).reshape(bins, bins)


# Point-cloud files per format (mpi_lidar.scans.pointcloud.POINT_CLOUD_FORMATS): the raw cloud as PLY beside the
# corrected one; LAS/LAZ hold the raw range as an extra dimension of the corrected cloud.
POINT_CLOUD_FILES = {"ply": ("raw.ply", "corrected.ply"), "las": ("corrected.las",), "laz": ("corrected.laz",)}
FULL_POINT_CLOUDS = ("ply", "las")  # written at level full unless ``point_clouds`` says otherwise
VIEW_3D_POINTS = 20_000  # most points per cloud in the interactive 3-D view of report.html
PLOTLY_JS = "plotly.min.js"
VIEW_3D_FALLBACK = "interactive 3-D view: open report.html"


def point_cloud_formats(outputs: str, point_clouds: tuple[str, ...] | list[str] | None = None) -> tuple[str, ...]:
    """The point-cloud formats a scan writes: ``point_clouds`` at any level (each once, in the order of
    :data:`POINT_CLOUD_FILES`), or by default :data:`FULL_POINT_CLOUDS` at level full and none below."""
    if point_clouds is None:
        return FULL_POINT_CLOUDS if check_outputs(outputs) == "full" else ()
    unknown = sorted(set(point_clouds) - set(POINT_CLOUD_FILES))
    if unknown:
        raise MpiLidarError(f"unknown point cloud format {unknown[0]!r}; choose from {', '.join(POINT_CLOUD_FILES)}")
    return tuple(fmt for fmt in POINT_CLOUD_FILES if fmt in point_clouds)


def point_cloud_files(scan: Scan, outputs: str, point_clouds: tuple[str, ...] | list[str] | None = None) -> list[str]:
    """The point-cloud files a scan's outputs hold at level ``outputs`` (none for a scan without geometry)."""
    if scan.ray_directions is None and (scan.azimuth_rad is None or scan.elevation_rad is None):
        return []
    return [name for fmt in point_cloud_formats(outputs, point_clouds) for name in POINT_CLOUD_FILES[fmt]]


def _write_point_clouds(directory: Path, formats: tuple[str, ...], raw_points: np.ndarray,
                        corrected_points: np.ndarray, fields: dict[str, np.ndarray]) -> list[str]:
    from mpi_lidar.scans.pointcloud import write_point_cloud  # laspy and plyfile only where clouds are written

    written = []
    for fmt in formats:
        for name in POINT_CLOUD_FILES[fmt]:
            points = raw_points if name.startswith("raw.") else corrected_points
            write_point_cloud(directory / name, fmt, points, fields)
            written.append(name)
    return written


def point_cloud_view_3d(raw_points: np.ndarray, corrected_points: np.ndarray, correction_mm: np.ndarray,
                        limit: int = VIEW_3D_POINTS) -> str:
    """An interactive plotly scatter3d of the raw and corrected points (grid (H, W, 3) [m]), both coloured by
    the applied correction [mm], as a ``<div>`` and its script (plotly.js itself not included: the page loads
    :data:`PLOTLY_JS`). At most ``limit`` points per cloud, evenly spread over the finite ones."""
    import plotly.graph_objects as go

    keep = np.flatnonzero(np.isfinite(raw_points.reshape(-1, 3)).all(axis=1)
                          & np.isfinite(corrected_points.reshape(-1, 3)).all(axis=1))
    if keep.size > limit:
        keep = keep[np.linspace(0, keep.size - 1, limit).round().astype(np.int64)]
    colour = np.nan_to_num(np.asarray(correction_mm, dtype=np.float32).reshape(-1)[keep], nan=0.0)
    span = max(float(np.quantile(np.abs(colour), 0.99)), 1e-3) if colour.size else 1.0
    fig = go.Figure()
    for name, points, size, opacity in (("raw", raw_points, 1.5, 0.45), ("corrected", corrected_points, 2.0, 1.0)):
        xyz = points.reshape(-1, 3)[keep].astype(np.float32)
        # plotly's z is up: x right, our z (forward) into plotly's y, our y (up) into plotly's z
        fig.add_trace(go.Scatter3d(x=xyz[:, 0], y=xyz[:, 2], z=xyz[:, 1], mode="markers", name=f"{name} points",
                                   marker={"size": size, "opacity": opacity, "color": colour,
                                           "coloraxis": "coloraxis"}))
    fig.update_layout(
        title=f"raw and corrected points ({keep.size:,} of each), coloured by the applied correction",
        coloraxis={"colorscale": "RdBu_r", "cmin": -span, "cmax": span,
                   "colorbar": {"title": {"text": "correction [mm]"}}},
        scene={"xaxis_title": "x [m]", "yaxis_title": "z (forward) [m]", "zaxis_title": "y (up) [m]",
               "aspectmode": "data"},
        legend={"x": 0.0, "y": 1.0}, margin={"l": 0, "r": 0, "t": 40, "b": 0}, autosize=True)
    return fig.to_html(include_plotlyjs=False, full_html=False, default_width="100%", default_height="600px",
                       config={"responsive": True, "displaylogo": False})


def write_plotly_js(directory: Path) -> Path:
    """plotly.js of the installed plotly package into ``directory`` (reports are read offline: no CDN)."""
    from importlib import resources

    source = resources.files("plotly") / "package_data" / PLOTLY_JS
    if source.is_file():
        data = source.read_bytes()
    else:  # pragma: no cover - a plotly that keeps its bundle elsewhere
        from plotly.offline import get_plotlyjs

        data = get_plotlyjs().encode("utf-8")
    target = directory / PLOTLY_JS
    target.write_bytes(data)
    return target


def metrics_table(metrics: dict[str, dict[str, float]]) -> Table:
    rows = []
    for region, m in metrics.items():
        rows.append((region, f"{m['pixels']:,}", f"{1e3 * m['raw_mae_m']:.3f}", f"{1e3 * m['corrected_mae_m']:.3f}",
                     f"{1e3 * m['raw_rmse_m']:.3f}", f"{1e3 * m['corrected_rmse_m']:.3f}",
                     f"{1e3 * m['raw_max_abs_m']:.2f}", f"{1e3 * m['corrected_max_abs_m']:.2f}"))
    return Table(("region", "pixels", "raw MAE [mm]", "corrected MAE [mm]", "raw RMSE [mm]", "corrected RMSE [mm]",
                  "raw max [mm]", "corrected max [mm]"), tuple(rows))


# Output levels of a corrected scan, from most to least; each holds what the next one holds.
OUTPUT_LEVELS = ("full", "light", "data")
# The default of a batch (``mpi-lidar correct``, the correction flow): the store, the report and a thumbnail
# cost little beside the correction itself; ``full`` (maps, histogram, point clouds as PLY and LAS, 3-D view)
# costs as much as the correction again on a megapixel scan (docs/benchmarks.md). The pipeline's three demo
# scenes are written ``full``.
DEFAULT_OUTPUTS = "light"
THUMBNAIL_PX = 512  # longest side of thumbnail.png [px]
THUMBNAIL_GAP_PX = 4


def check_outputs(outputs: str) -> str:
    """``outputs`` if it names an output level; one clear error otherwise."""
    if outputs not in OUTPUT_LEVELS:
        raise MpiLidarError(f"unknown output level {outputs!r}; choose one of {', '.join(OUTPUT_LEVELS)}")
    return outputs


def covers(written: str | None, wanted: str) -> bool:
    """Whether outputs written at level ``written`` hold everything of level ``wanted`` (None: written
    before output levels existed, that is everything)."""
    written = written if written in OUTPUT_LEVELS else "full"
    return OUTPUT_LEVELS.index(written) <= OUTPUT_LEVELS.index(check_outputs(wanted))


def write_scan_outputs(target: Path, scan: Scan, correction: Correction,
                       metrics: dict[str, dict[str, float]] | Future[dict[str, dict[str, float]]],
                       identity: dict[str, str], options: CorrectionOptions, outputs: str = "full",
                       cpu_s: dict[str, float] | None = None,
                       point_clouds: tuple[str, ...] | list[str] | None = None) -> list[str]:
    """One scan's outputs at level ``outputs``, written into a staging directory and swapped in at the end.

    ``data``: ``corrected.zarr`` and ``metrics.json`` (counts, metrics, notes, the outputs written);
    ``light``: those, ``report.md``/``report.html`` and ``thumbnail.png`` (corrected depth and flags, at most
    :data:`THUMBNAIL_PX` pixels wide); ``full``: those but the thumbnail, plus the maps, the error histogram,
    the point-cloud views, an interactive 3-D view in report.html (with ``plotly.min.js`` beside it) and the
    point clouds. ``point_clouds``: the formats written at any level (:data:`POINT_CLOUD_FILES`: ``ply``
    writes ``raw.ply`` and ``corrected.ply``, ``las``/``laz`` ``corrected.las``/``.laz``, every file with the
    named fields of :func:`mpi_lidar.scans.pointcloud.correction_fields`); None: ``ply`` and ``las`` at
    level full, none below. ``metrics`` are :func:`scan_metrics`, or a future of them (the store is written
    while they are worked out). Returns the notes for the batch summary; ``cpu_s``, if given, gets the CPU
    seconds of this process spent on ``write`` (store, point clouds, report, and a future's metrics) and
    ``figures`` (drawing and encoding PNGs, the 3-D view).
    """
    check_outputs(outputs)
    formats = point_cloud_formats(outputs, point_clouds)
    cpu_s = {} if cpu_s is None else cpu_s
    notes: list[str] = list(correction.notes)
    if scan.reference_depth is None:
        notes.append("no reference depth: errors, error maps and histogram skipped")
    try:
        with atomic_path(target, replace=True, what="scan outputs") as staging, ThreadPoolExecutor(1) as beside:
            staging.mkdir()
            # The thumbnail needs nothing of the store: it is drawn on a thread beside the store's writing.
            thumbnail = (beside.submit(_thread_cpu, _write_thumbnail, staging, correction) if outputs == "light"
                         else None)
            started = time.process_time()
            _write_corrected_store(staging / "corrected.zarr", scan, correction, identity, options, outputs)
            depth_limits, thumbnail_cpu = thumbnail.result() if thumbnail is not None else (None, 0.0)
            if isinstance(metrics, Future):
                metrics = metrics.result()
            cpu_s["figures"] = cpu_s.get("figures", 0.0) + thumbnail_cpu
            cpu_s["write"] = cpu_s.get("write", 0.0) + time.process_time() - started - thumbnail_cpu
            figures: dict[str, plt.Figure] = {}
            files = ["corrected.zarr"]
            embeds: list[Embed] = []
            if outputs == "full":
                with _cpu(cpu_s, "figures"):
                    figures["maps.png"] = maps_figure(scan, correction)
                    if scan.reference_depth is not None:
                        where = _regions(scan, correction)["whole map"]
                        figures["error_hist.png"] = error_histogram_figure(
                            {f"raw {scan.frequencies_hz[-1] / 1e6:g} MHz":
                             1e3 * (scan.depth[-1] - scan.reference_depth)[where],
                             "corrected": 1e3 * (correction.depth - scan.reference_depth)[where]}, "depth error [mm]")
            rays = scan.rays() if outputs == "full" or formats else None
            if rays is not None:
                from mpi_lidar.scans.pointcloud import correction_fields

                with _cpu(cpu_s, "write"):
                    raw_points = geometry.point_cloud(
                        np.where(np.isfinite(correction.depth), scan.depth[-1], np.nan), rays)
                    corrected_points = geometry.point_cloud(correction.depth, rays)
                    del rays
                    fields = correction_fields(scan.depth[-1], correction.depth, correction.flags,
                                               scan.amplitude[-1])
                    files += _write_point_clouds(staging, formats, raw_points, corrected_points, fields)
                if outputs == "full":
                    with _cpu(cpu_s, "figures"):
                        figures["point_cloud.png"] = point_cloud_figure(raw_points, corrected_points)
                        embeds.append(Embed(point_cloud_view_3d(raw_points, corrected_points,
                                                                fields["correction_mm"]),
                                            fallback=VIEW_3D_FALLBACK, scripts=(PLOTLY_JS,)))
                        write_plotly_js(staging)
                        files.append(PLOTLY_JS)
                del raw_points, corrected_points, fields
            elif outputs == "full":
                notes.append("no scan geometry: point clouds and views skipped")
            elif formats:
                notes.append("no scan geometry: point clouds skipped")
            if outputs == "full":
                with _cpu(cpu_s, "figures"):
                    for name, fig in figures.items():
                        save_figure(fig, staging / name)
            images = sorted(figures) if outputs == "full" else ["thumbnail.png"] if outputs == "light" else []
            files += images + ([] if outputs == "data" else ["report.md", "report.html"]) + ["metrics.json"]
            with _cpu(cpu_s, "write"):
                captions = {"thumbnail.png": thumbnail_legend(depth_limits)} if outputs == "light" else None
                report = scan_report(scan, correction, metrics, notes, images, outputs, files, captions, embeds)
                if outputs != "data":
                    (staging / "report.md").write_text(report.markdown())
                    (staging / "report.html").write_text(report.html())
                (staging / "metrics.json").write_text(json.dumps(report.data, indent=2, sort_keys=True) + "\n")
                (staging / REPORT_MARKER).write_text("")
    finally:
        plt.close("all")
    return notes


def _write_thumbnail(staging: Path, correction: Correction) -> tuple[float, float]:
    """``thumbnail.png`` of the correction in ``staging``; returns the depth limits of its colour scale [m]."""
    image, depth_limits = thumbnail_image(correction)
    write_png(staging / "thumbnail.png", image)
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


def thumbnail_image(correction: Correction, limit: int = THUMBNAIL_PX) -> tuple[np.ndarray, tuple[float, float]]:
    """RGB image (h, w, 3) uint8, at most ``limit`` pixels on its longest side: the corrected depth (left,
    viridis between its 1 and 99 % quantiles, invalid pixels white) and the flags (right, :data:`FLAG_COLOURS`),
    every ``step``-th pixel of each. Returns the image and the depth range of the colours [m]."""
    h, w = correction.flags.shape
    panel = max(1, (limit - THUMBNAIL_GAP_PX) // 2)
    step = max(1, -(-h // limit), -(-w // panel))
    depth, flags = correction.depth[::step, ::step], correction.flags[::step, ::step]
    finite = depth[np.isfinite(depth)]
    low, high = (float(v) for v in np.quantile(finite, [0.01, 0.99])) if finite.size else (0.0, 1.0)
    scaled = np.clip((np.nan_to_num(depth, nan=low) - low) / max(high - low, 1e-9), 0.0, 1.0)
    left = matplotlib.colormaps["viridis"](scaled, bytes=True)[..., :3]
    left[~np.isfinite(depth)] = 255
    palette = np.array([[int(c[i:i + 2], 16) for i in (1, 3, 5)] for c in FLAG_COLOURS], dtype=np.uint8)
    right = palette[np.minimum(flags, len(FLAG_COLOURS) - 1)]
    ph, pw = flags.shape
    image = np.full((ph, 2 * pw + THUMBNAIL_GAP_PX, 3), 255, dtype=np.uint8)
    image[:, :pw], image[:, pw + THUMBNAIL_GAP_PX:] = left, right
    return image, (low, high)


def thumbnail_legend(depth_limits: tuple[float, float]) -> str:
    flags = ", ".join(f"{flag.name.lower().replace('_', ' ')} {colour}" for flag, colour in zip(Flag, FLAG_COLOURS,
                                                                                                  strict=True))
    return (f"Thumbnail: corrected depth (left; viridis from {depth_limits[0]:.3f} to {depth_limits[1]:.3f} m, "
            f"invalid pixels white) and what was done per pixel (right; {flags}).")


def write_png(path: Path, image: np.ndarray) -> None:
    """An RGB image (h, w, 3) uint8 as a PNG, without drawing a figure."""
    matplotlib.image.imsave(path, image, format="png")


CORRECTED_METADATA = {
    "corrected_depth": ("m", "corrected range along the ray"),
    "flags": ("1", "what was done to the pixel"),
    "multipath_bias_m": ("m", "expected multipath bias (geometry gate)"),
}


def _write_corrected_store(path: Path, scan: Scan, correction: Correction, identity: dict[str, str],
                           options: CorrectionOptions, outputs: str = "full") -> None:
    """``corrected.zarr``: the corrected depth, the flags and the bias map, readable by ``xarray.open_zarr``.

    Like a scan store: the scan grid's coordinates (``azimuth_rad``/``elevation_rad``, else the pixel indices
    ``y``/``x``), ``units`` and ``long_name`` on every array, CF ``flag_values``/``flag_meanings`` on ``flags``,
    fingerprints of every array, then consolidated metadata.
    """
    group = zarr.open_group(store=str(path), mode="w-")
    arrays = {"corrected_depth": (correction.depth, ("y", "x")), "flags": (correction.flags, ("y", "x"))}
    if correction.multipath_bias_m is not None:
        arrays["multipath_bias_m"] = (correction.multipath_bias_m, ("y", "x"))
    for name, dims in (("azimuth_rad", ("x",)), ("elevation_rad", ("y",))):
        if getattr(scan, name) is not None:
            arrays[name] = (np.asarray(getattr(scan, name)), dims)
    flags = {"flag_values": [int(f) for f in Flag], "flag_meanings": " ".join(f.name.lower() for f in Flag)}
    write_described_arrays(group, arrays, scan.shape, metadata=CORRECTED_METADATA, attributes={"flags": flags})
    # One metadata write: group.attrs.update would rewrite the group's metadata once per key.
    group.update_attributes({"schema": CORRECTED_SCHEMA, "scan_name": scan.name, **identity,
                             "options": options.model_dump(), "flag_codes": {f.name.lower(): int(f) for f in Flag},
                             "counts": correction.counts(), "frequencies_hz": list(scan.frequencies_hz),
                             **({} if correction.calibration is None else {"footprint": footprint_record(correction)}),
                             "outputs": outputs, "chunk_sha256": store_fingerprints(group)})
    consolidate(path)


def scan_report(scan: Scan, correction: Correction, metrics: dict[str, dict[str, float]], notes: list[str],
                figures: list[str], outputs: str = "full", files: list[str] | None = None,
                captions: dict[str, str] | None = None, embeds: list[Embed] | None = None) -> Report:
    """The scan's report: what was done per pixel, errors, notes, which outputs were written, the figures
    (each after its caption in ``captions``, if any) and then the ``embeds`` (the interactive 3-D view)."""
    counts = correction.counts()
    total = max(sum(counts.values()), 1)
    flags = Table(("pixels", "count", "share"),
                  tuple((name.replace("_", " "), f"{n:,}", f"{100 * n / total:.1f} %") for name, n in counts.items()))
    blocks: list = [f"Scan `{scan.name}`, {scan.shape[0]} x {scan.shape[1]} pixels at "
                    + ", ".join(f"{f / 1e6:g}" for f in scan.frequencies_hz) + " MHz. "
                    f"Correction {correction.total_s:.2f} s (gate {correction.gate_s:.2f} s, inference "
                    f"{correction.inference_s:.2f} s).", flags]
    if metrics:
        blocks.append(metrics_table(metrics))
    files = sorted(files if files is not None else ["corrected.zarr", *figures, "metrics.json", "report.html",
                                                    "report.md"])
    more = {"data": " Level light adds this report and a thumbnail; full the maps, histogram and point clouds.",
            "light": " Level full adds the maps, the error histogram, the point-cloud views and point clouds.",
            "full": ""}[outputs]
    blocks += [*notes, f"Outputs (level {outputs}): {', '.join(files)}.{more}"]
    for name in figures:
        blocks += [captions[name]] if captions and name in captions else []
        blocks.append(Path(name))
    blocks += embeds or []
    return Report(title=f"Correction of {scan.name}", blocks=blocks,
                  data={"scan": scan.name, "counts": counts, "metrics": metrics, "notes": notes,
                        "outputs": {"level": outputs, "files": files},
                        "seconds": {"total": correction.total_s, "gate": correction.gate_s,
                                    "inference": correction.inference_s},
                        **({} if correction.calibration is None else {"footprint": footprint_record(correction)})})


def footprint_record(correction: Correction) -> dict[str, object]:
    """The scan's own footprint estimate, and the pixels it decided: corrected with it, or left as measured."""
    counts = correction.counts()
    estimate = correction.calibration
    return {"mode": "auto", **estimate.to_dict(),
            "pixels_corrected_with_it": counts["corrected"] if estimate.significant else 0,
            "pixels_left_uncalibrated": counts["uncalibrated"]}


def batch_report(outcomes: list[ScanOutcome], wall_s: float, summary_dir: Path | None = None) -> Report:
    """One table over the batch: per scan its name, status, gated-out and invalid shares, MAE before/after on
    the whole map and the mask, notes and source path; above it a line counting every status.

    Gated out: valid pixels left as measured because the gate found no need (no multipath potential, or
    not needed by a pixel-wise gate), as a share of all pixels. Invalid: pixels flagged not finite, no
    return, saturated or inconsistent, as a share of all pixels. A skipped scan shows the numbers of its
    existing outputs, and its notes say the status those earned. With ``summary_dir`` (where the summary is
    written) a last column links each scan's own report.
    """
    rows = []
    for o in outcomes:
        total = max(sum(o.counts.values()), 1)
        gated = sum(o.counts.get(name, 0) for name in GATED_OUT)
        not_needed = f"{100 * gated / total:.1f} %" if o.counts else ""
        invalid = f"{100 * invalid_share(o.counts):.1f} %" if o.counts else ""
        whole, masked = o.metrics.get("whole map", {}), o.metrics.get("masked region", {})
        reason = f"{o.reason} ({o.kept_status})" if o.kept_status else o.reason
        rows.append(tuple(_cell(c) for c in (
            o.name, o.status, not_needed, invalid, _mm(whole, "raw_mae_m"), _mm(whole, "corrected_mae_m"),
            _mm(masked, "raw_mae_m"), _mm(masked, "corrected_mae_m"), f"{o.seconds:.2f}",
            "; ".join(n for n in (reason, *o.notes) if n), o.source)) + _report_link(o, summary_dir))
    headers = ("scan", "status", "gated out", "invalid", "raw MAE [mm]", "corrected MAE [mm]", "masked raw MAE [mm]",
               "masked corrected MAE [mm]", "seconds", "notes", "source")
    table = Table(headers + (("report",) if summary_dir is not None else ()), tuple(rows))
    labels = {ScanStatus.SKIPPED: "already done"}
    counted = ", ".join(f"{sum(o.status == status for o in outcomes)} {labels.get(status, status.value)}"
                        for status in ScanStatus)
    summary = f"{len(outcomes)} scans in {wall_s:.1f} s: {counted}."
    return Report(title="Batch correction", blocks=[summary, table],
                  data={"wall_s": wall_s, "scans": [o.__dict__ for o in outcomes]})


def _cell(text: object) -> str:
    """One table cell of plain text: one line, no ``|`` that would split a markdown row, no markup."""
    text = " ".join(str(text).splitlines())
    for special in ("\\", "|", "*", "[", "]", "`"):
        text = text.replace(special, "\\" + special)
    return text


def _report_link(outcome: ScanOutcome, summary_dir: Path | None) -> tuple[str, ...]:
    """The link cell from the summary to the scan's own report, where one was written."""
    if summary_dir is None:
        return ()
    report = Path(outcome.output) / "report.html" if outcome.output else None
    if report is None or not report.is_file():
        return ("",)
    return (f"[report]({Path(os.path.relpath(report, summary_dir)).as_posix()})",)


def _mm(metrics: dict[str, float], key: str) -> str:
    value = metrics.get(key) if isinstance(metrics, dict) else None
    return f"{1e3 * value:.3f}" if isinstance(value, int | float) else ""


def write_batch_report(outcomes: list[ScanOutcome], wall_s: float, out_dir: str | Path) -> Path:
    """The batch summary into ``<out_dir>/summary/`` (a name no scan's outputs take, see correct_archive)."""
    summary_dir = Path(out_dir) / "summary"
    return write_report(batch_report(outcomes, wall_s, summary_dir), summary_dir, {})
