"""Figures of a corrected scan at level full: the maps, the point-cloud views and the interactive 3-D view.

Every figure is a :class:`matplotlib.figure.Figure` of its own, drawn without pyplot: nothing of pyplot's
global state (its backend, its open figures) is touched, and ``Figure.savefig`` renders with the Agg canvas.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
from matplotlib.axes import Axes
from matplotlib.colors import ListedColormap
from matplotlib.figure import Figure
from matplotlib.ticker import MaxNLocator

from mpi_lidar.correction import Correction, Flag
from mpi_lidar.reporting.metrics import amplitude_v2, applied_correction_mm, measured_depth
from mpi_lidar.reporting.thumbnail import FLAG_COLOURS
from mpi_lidar.scans.scan import Scan
from mpi_lidar.storage.atomic import atomic_path

VIEW_3D_POINTS = 20_000  # most points per cloud in the interactive 3-D view of report.html
PLOTLY_JS = "plotly.min.js"
VIEW_3D_FALLBACK = "interactive 3-D view: open report.html"


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


def maps_figure(scan: Scan, correction: Correction) -> Figure:
    """Raw and corrected depth, amplitude, what correction did and the flag map; with a reference depth also
    the error maps before and after (Fig. 7/8 b-f).

    Without a reference (every archived scan) the second row shows the applied correction (corrected minus
    raw depth, where corrected), the geometry gate's expected multipath bias and the flags; with one, the
    applied correction joins the first row and the error maps the second. Axes in degrees of azimuth and
    elevation where the scan has that grid, pixel indices otherwise.
    """
    reference_depth = scan.reference_depth
    reference = reference_depth is not None
    columns = 4 if reference else 3
    # Sized for a report page (about 1150 pixels wide at 120 dpi), so its text is read at about its size.
    fig = Figure(figsize=(3.4 * columns, 6.4), layout="constrained")
    axes = fig.subplots(2, columns, squeeze=False)
    grid = grid_axes(scan)
    label = f"{scan.frequencies_hz[-1] / 1e6:g} MHz"
    raw_depth = measured_depth(scan, correction)
    finite = raw_depth[np.isfinite(correction.depth)]
    limits = np.quantile(finite, [0.01, 0.99]) if finite.size else (0.0, 1.0)
    _image(axes[0, 0], raw_depth, f"raw depth {label} [m]", "viridis", limits, grid)
    _image(axes[0, 1], correction.depth, "corrected depth [m]", "viridis", limits, grid)
    _image(axes[0, 2], amplitude_v2(scan, correction), f"amplitude {label} [V$^2$]", "magma", None, grid)
    applied = applied_correction_mm(scan, correction)
    shown = np.abs(applied[np.isfinite(applied)])
    span = max(float(np.quantile(shown, 0.99)), 1e-3) if shown.size else 1.0
    applied_ax = axes[0, 3] if reference else axes[1, 0]
    if shown.size:
        _image(applied_ax, applied, f"applied correction [mm]\n({shown.size:,} pixels corrected)", "RdBu_r",
               (-span, span), grid)
    else:
        _words(applied_ax, "applied correction:\nno pixel was corrected")
    if reference_depth is not None:
        raw_error = 1e3 * (raw_depth - reference_depth)
        corrected_error = 1e3 * (correction.depth - reference_depth)
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
        _image(bias_ax, bias, "expected multipath\nbias [mm]", "cividis", (0.0, top), grid)
    else:
        _words(bias_ax, "expected multipath bias:\ncomputed by the geometry gate only")
    flag_ax = axes[1, -1]
    flag_image = flag_ax.imshow(correction.flags, cmap=ListedColormap(FLAG_COLOURS), vmin=-0.5,
                                vmax=len(Flag) - 0.5, interpolation="nearest", extent=grid[0])
    bar = fig.colorbar(flag_image, ax=flag_ax, ticks=range(len(Flag)))
    bar.ax.set_yticklabels([f.name.lower().replace("_", " ") for f in Flag])
    flag_ax.set_title("what was done\nper pixel", fontsize="medium")
    flag_ax.set_xlabel(grid[1])
    flag_ax.set_ylabel(grid[2])
    fig.suptitle(f"scan {scan.name}")
    return fig


def _words(ax: Axes, text: str) -> None:
    """A panel that has nothing to draw says why in words."""
    ax.text(0.5, 0.5, text, ha="center", va="center", transform=ax.transAxes)
    ax.set_axis_off()


def _image(ax: Axes, values: np.ndarray, title: str, cmap: str, limits,
           grid: tuple[tuple[float, float, float, float] | None, str, str]) -> None:
    shown = ax.imshow(values, cmap=cmap, vmin=None if limits is None else limits[0],
                      vmax=None if limits is None else limits[1], interpolation="nearest", extent=grid[0])
    ax.figure.colorbar(shown, ax=ax)
    ax.set_title(title, fontsize="medium")
    ax.set_xlabel(grid[1])
    ax.set_ylabel(grid[2])


POINT_CLOUD_BINS = 400  # most cells along a rasterized view's longer side: a million points cost what a thousand do
POINT_CLOUD_MIN_ASPECT = 1 / 2  # a view's short side spans at least this share of its long one
POINT_CLOUD_PANEL_IN = 4.2  # width of one view in point_cloud.png [in]


def point_cloud_figure(raw_points: np.ndarray, corrected_points: np.ndarray) -> Figure:
    """Top and side views of the raw and corrected point clouds (Fig. 9), rasterized.

    Each view is a 2-D histogram of the points on square cells, coloured by the mean of the coordinate it
    hides, so drawing costs the same for a thousand points as for ten million; both columns of a row share
    their extents and colour bar (below them). Axes are to scale; each row is as tall as its views need (a
    tall view no taller than a square one). A view whose points span much less on one axis than on the other
    (a flat wall seen from above) is widened on that axis to :data:`POINT_CLOUD_MIN_ASPECT` of the other, so
    it shows as a thin band in a readable box instead of a line with its ticks on top of each other.
    """
    finite = [p.reshape(-1, 3)[np.isfinite(p.reshape(-1, 3)).all(axis=1)] for p in (raw_points, corrected_points)]
    views = (("top view", 0, 2, 1, "x [m]", "z (forward) [m]"), ("side view", 2, 1, 0, "z (forward) [m]", "y (up) [m]"))
    extents = [_view_extent(finite, u, v) for _, u, v, *_ in views]
    ratios = [(e[3] - e[2]) / (e[1] - e[0]) for e in extents]
    heights = [min(r, 1.0) for r in ratios]  # a tall view is as high as a square one, and narrower
    fig = Figure(figsize=(2 * POINT_CLOUD_PANEL_IN + 1.2, POINT_CLOUD_PANEL_IN * sum(heights) + 3.2),
                 layout="constrained")
    axes = fig.subplots(2, 2, squeeze=False, gridspec_kw={"height_ratios": heights})
    # Cells about as fine as the points are dense: a small scan's surfaces show as bands, not scattered dots.
    bins = int(np.clip(2 * np.sqrt(max(c.shape[0] for c in finite)), POINT_CLOUD_BINS // 4, POINT_CLOUD_BINS))
    for row, ((title, u, v, colour, xlabel, ylabel), extent) in enumerate(zip(views, extents, strict=True)):
        hidden = np.concatenate([c[:, colour] for c in finite])
        low, high = np.quantile(hidden, [0.01, 0.99]) if hidden.size else (0.0, 1.0)
        for column, (label, points) in enumerate(zip(("raw", "corrected"), finite, strict=True)):
            ax = axes[row, column]
            image = _mean_raster(points[:, u], points[:, v], points[:, colour], extent, bins)
            shown = ax.imshow(image, origin="lower", extent=extent, cmap="viridis", interpolation="nearest",
                              aspect="equal", vmin=low, vmax=high)
            ax.set_title(f"{label}: {title} ({points.shape[0]:,} points)", fontsize="medium")
            ax.set_xlabel(xlabel)
            ax.set_ylabel(ylabel)
            # Ticks by the side's length: a short side gets fewer, so their labels never overlap.
            ax.xaxis.set_major_locator(MaxNLocator(max(3, round(6 / max(ratios[row], 1.0)))))
            ax.yaxis.set_major_locator(MaxNLocator(max(3, round(6 * min(ratios[row], 1.0)))))
        fig.colorbar(shown, ax=axes[row, :], orientation="horizontal", shrink=0.5, aspect=40,
                     label=f"{'xyz'[colour]} [m] (mean per cell)")
    return fig


def _view_extent(clouds: list[np.ndarray], u: int, v: int) -> tuple[float, float, float, float]:
    both = np.concatenate([c[:, [u, v]] for c in clouds]) if any(c.size for c in clouds) else np.zeros((1, 2))
    low, high = both.min(axis=0), both.max(axis=0)
    pad = np.maximum(1e-3, 0.02 * (high - low))
    low, high = low - pad, high + pad
    centre, span = 0.5 * (low + high), high - low
    span = np.maximum(span, POINT_CLOUD_MIN_ASPECT * span.max())
    low, high = centre - 0.5 * span, centre + 0.5 * span
    return (float(low[0]), float(high[0]), float(low[1]), float(high[1]))


def _mean_raster(u: np.ndarray, v: np.ndarray, value: np.ndarray, extent: tuple[float, float, float, float],
                 bins: int = POINT_CLOUD_BINS) -> np.ndarray:
    """Mean of ``value`` per square cell of a grid over ``extent`` (rows along v), ``bins`` cells along its
    longer side; NaN where empty."""
    du, dv = extent[1] - extent[0], extent[3] - extent[2]
    cell = max(du, dv) / bins
    columns, rows = max(1, round(du / cell)), max(1, round(dv / cell))
    column = np.clip(((u - extent[0]) / du * columns).astype(np.int64), 0, columns - 1)
    row = np.clip(((v - extent[2]) / dv * rows).astype(np.int64), 0, rows - 1)
    index = row * columns + column
    count = np.bincount(index, minlength=rows * columns)
    total = np.bincount(index, weights=value, minlength=rows * columns)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(count > 0, total / count, np.nan).reshape(rows, columns)


def point_cloud_view_3d(raw_points: np.ndarray, corrected_points: np.ndarray, correction_mm: np.ndarray,
                        limit: int = VIEW_3D_POINTS) -> str:
    """An interactive plotly scatter3d of the raw and corrected points (grid (H, W, 3) [m]), both coloured by
    the applied correction [mm], as a ``<div>`` and its script (plotly.js itself not included: the page loads
    :data:`PLOTLY_JS`). At most ``limit`` points per cloud, evenly spread over the finite ones. The box is to
    scale, no side shorter than :data:`POINT_CLOUD_MIN_ASPECT` of the longest (a flat wall stays a plane in view),
    seen from the sensor's side from a distance that shows all of it."""
    import plotly.graph_objects as go

    keep = np.flatnonzero(np.isfinite(raw_points.reshape(-1, 3)).all(axis=1)
                          & np.isfinite(corrected_points.reshape(-1, 3)).all(axis=1))
    if keep.size > limit:
        keep = keep[np.linspace(0, keep.size - 1, limit).round().astype(np.int64)]
    colour = np.nan_to_num(np.asarray(correction_mm, dtype=np.float32).reshape(-1)[keep], nan=0.0)
    span = max(float(np.quantile(np.abs(colour), 0.99)), 1e-3) if colour.size else 1.0
    fig = go.Figure()
    shown = [points.reshape(-1, 3)[keep].astype(np.float32) for points in (raw_points, corrected_points)]
    for name, xyz, size, opacity in (("raw", shown[0], 1.5, 0.45), ("corrected", shown[1], 2.0, 1.0)):
        # plotly's z is up: x right, our z (forward) into plotly's y, our y (up) into plotly's z
        fig.add_trace(go.Scatter3d(x=xyz[:, 0], y=xyz[:, 2], z=xyz[:, 1], mode="markers", name=f"{name} points",
                                   marker={"size": size, "opacity": opacity, "color": colour,
                                           "coloraxis": "coloraxis"}))
    fig.update_layout(
        title=f"raw and corrected points ({keep.size:,} of each), coloured by the applied correction",
        coloraxis={"colorscale": "RdBu_r", "cmin": -span, "cmax": span,
                   "colorbar": {"title": {"text": "correction [mm]"}}},
        scene={**_scene_box(np.concatenate(shown)), "camera": {"eye": {"x": 1.6, "y": -1.9, "z": 1.1}}},
        legend={"x": 0.0, "y": 1.0}, margin={"l": 0, "r": 0, "t": 40, "b": 0}, autosize=True)
    return fig.to_html(include_plotlyjs=False, full_html=False, default_width="100%", default_height="640px",
                       config={"responsive": True, "displaylogo": False})


def _scene_box(xyz: np.ndarray) -> dict[str, object]:
    """plotly's scene axes around points (n, 3) [m] in our axes (x, y up, z forward): each axis's range about
    its points, no shorter than :data:`POINT_CLOUD_MIN_ASPECT` of the longest, and the box to that scale."""
    low, high = (xyz.min(axis=0), xyz.max(axis=0)) if xyz.size else (np.zeros(3), np.ones(3))
    spans = np.maximum(high - low, POINT_CLOUD_MIN_ASPECT * max(float((high - low).max()), 1e-3))
    centre, ratio = 0.5 * (low + high), spans / spans.max()
    scene: dict[str, object] = {"aspectmode": "manual"}
    for ours, theirs, title in ((0, "x", "x [m]"), (2, "y", "z (forward) [m]"), (1, "z", "y (up) [m]")):
        half = 0.5 * float(spans[ours])  # plotly's z is up: our y
        scene[f"{theirs}axis"] = {"title": {"text": title},
                                  "range": [float(centre[ours]) - half, float(centre[ours]) + half]}
    scene["aspectratio"] = {"x": float(ratio[0]), "y": float(ratio[2]), "z": float(ratio[1])}
    return scene


def write_plotly_js(directory: Path) -> Path:
    """plotly.js of the installed plotly package into ``directory`` (reports are read offline: no CDN), once.

    One bundle serves every scan report of a batch (they link to it relatively): a bundle already there of the
    same size is kept; otherwise it is written through a temporary file and a rename, so scans written at
    once by several processes never see half of it.
    """
    from importlib import resources

    source = resources.files("plotly") / "package_data" / PLOTLY_JS
    if source.is_file():
        data = source.read_bytes()
    else:  # pragma: no cover - a plotly that keeps its bundle elsewhere
        from plotly.offline import get_plotlyjs

        data = get_plotlyjs().encode("utf-8")
    target = directory / PLOTLY_JS
    if target.is_file() and target.stat().st_size == len(data):
        return target
    directory.mkdir(parents=True, exist_ok=True)
    with atomic_path(target, replace=True, what="plotly bundle") as staging:
        staging.write_bytes(data)
    return target


def plotly_js_src(bundle: Path, page_dir: Path) -> str:
    """The ``src`` of the plotly bundle for a page in ``page_dir``: relative, so a batch folder moves whole."""
    return Path(os.path.relpath(bundle, page_dir)).as_posix()
