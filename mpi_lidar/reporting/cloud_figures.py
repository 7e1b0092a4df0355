"""Figures of a corrected scan's points at level full: the top views and side profile of point_cloud.png, and the
interactive 3-D view of report.html with its one shared plotly.js bundle.

Every figure is a :class:`matplotlib.figure.Figure` of its own, drawn without pyplot (see
:mod:`mpi_lidar.reporting.figures`).
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
from matplotlib.figure import Figure
from matplotlib.ticker import MaxNLocator

from mpi_lidar.storage.atomic import atomic_path

VIEW_3D_POINTS = 20_000  # most points per cloud in the interactive 3-D view of report.html
PLOTLY_JS = "plotly.min.js"
VIEW_3D_FALLBACK = "interactive 3-D view: open report.html"


POINT_CLOUD_BINS = 400  # most cells along a rasterized view's longer side: a million points cost what a thousand do
POINT_CLOUD_MIN_ASPECT = 1 / 2  # a view's short side spans at least this share of its long one
POINT_CLOUD_PANEL_IN = 4.2  # width of one view in point_cloud.png [in]


def point_cloud_figure(raw_points: np.ndarray, corrected_points: np.ndarray) -> Figure:
    """Top views of the raw and corrected point clouds (Fig. 9), rasterized, and a side profile of one column.

    Each top view is a 2-D histogram of the points (grid (H, W, 3) [m]) on square cells, coloured by the mean
    height of the points in a cell, so drawing costs the same for a thousand points as for ten million; both share
    their extents and colour bar (below them). They are seen from above, forward up the page, so +x (the scanner's
    left, in the scan frame) is on the left. Axes are to scale; a view whose points span much less on one axis
    than on the other (a flat wall seen from above) is widened on that axis to :data:`POINT_CLOUD_MIN_ASPECT` of
    the other, so it shows as a thin band in a readable box instead of a line with its ticks on top of each other.

    Under them, the side profile: the points of the middle column (or the nearest column with points) seen from
    the scanner's right, height against forward distance, raw and corrected together and to scale; beside it how
    far correction moved each of them along its ray [mm], against the same heights.
    """
    finite = [p.reshape(-1, 3)[np.isfinite(p.reshape(-1, 3)).all(axis=1)] for p in (raw_points, corrected_points)]
    extent = _view_extent(finite, 0, 2)
    ratio = (extent[3] - extent[2]) / (extent[1] - extent[0])
    height = min(ratio, 1.0)  # a deep view is as high as a square one, and narrower
    fig = Figure(figsize=(2 * POINT_CLOUD_PANEL_IN + 1.2, POINT_CLOUD_PANEL_IN * (height + PROFILE_HEIGHT) + 2.6),
                 layout="constrained")
    axes = fig.subplots(2, 2, squeeze=False, gridspec_kw={"height_ratios": [height, PROFILE_HEIGHT]})
    _top_views(fig, axes[0], finite, extent, ratio)
    _side_profile(axes[1], raw_points, corrected_points)
    return fig


PROFILE_HEIGHT = 0.8  # the side profile's row, against a square top view's


def _top_views(fig: Figure, axes: np.ndarray, finite: list[np.ndarray], extent: tuple[float, float, float, float],
               ratio: float) -> None:
    # Cells about as fine as the points are dense: a small scan's surfaces show as bands, not scattered dots.
    bins = int(np.clip(2 * np.sqrt(max(c.shape[0] for c in finite)), POINT_CLOUD_BINS // 4, POINT_CLOUD_BINS))
    hidden = np.concatenate([c[:, 1] for c in finite])
    low, high = np.quantile(hidden, [0.01, 0.99]) if hidden.size else (0.0, 1.0)
    for ax, label, points in zip(axes, ("raw", "corrected"), finite, strict=True):
        image = _mean_raster(points[:, 0], points[:, 2], points[:, 1], extent, bins)
        shown = ax.imshow(image, origin="lower", extent=extent, cmap="viridis", interpolation="nearest",
                          aspect="equal", vmin=low, vmax=high)
        ax.set_title(f"{label}: top view ({points.shape[0]:,} points)", fontsize="medium")
        ax.set_xlabel("x (the scanner's left) [m]")
        ax.set_ylabel("z (forward) [m]")
        ax.set_xlim(extent[1], extent[0])  # seen from above, forward up the page: +x on the left
        # Ticks by the side's length: a short side gets fewer, so their labels never overlap.
        ax.xaxis.set_major_locator(MaxNLocator(max(3, round(6 / max(ratio, 1.0)))))
        ax.yaxis.set_major_locator(MaxNLocator(max(3, round(6 * min(ratio, 1.0)))))
    fig.colorbar(shown, ax=list(axes), orientation="horizontal", shrink=0.5, aspect=40,
                 label="y (up) [m] (mean per cell)")


def profile_column(raw_points: np.ndarray, corrected_points: np.ndarray) -> int:
    """The column of the grids (H, W, 3) the side profile shows: the middle one, or the nearest to it with the
    most points where it has none (ties: the nearer)."""
    both = np.isfinite(raw_points).all(axis=-1) & np.isfinite(corrected_points).all(axis=-1)
    counts = both.sum(axis=0)
    w = counts.size
    middle = w // 2
    if counts[middle] >= 2 or not counts.any():
        return middle
    order = np.argsort(np.abs(np.arange(w) - middle), kind="stable")
    return int(order[np.argmax(counts[order] == counts.max())])


def _side_profile(axes: np.ndarray, raw_points: np.ndarray, corrected_points: np.ndarray) -> None:
    column = profile_column(raw_points, corrected_points)
    raw, corrected = raw_points[:, column].astype(np.float64), corrected_points[:, column].astype(np.float64)
    both = np.isfinite(raw).all(axis=1) & np.isfinite(corrected).all(axis=1)
    raw, corrected = raw[both], corrected[both]
    profile, change = axes
    extent = _view_extent([raw, corrected], 2, 1)
    profile.plot(raw[:, 2], raw[:, 1], ".", color="#8395a7", markersize=3, label="raw")
    profile.plot(corrected[:, 2], corrected[:, 1], ".", color="#2e86de", markersize=3, label="corrected")
    profile.set(xlim=extent[:2], ylim=extent[2:], aspect="equal")
    profile.set_title(f"side profile: column {column} ({both.sum():,} points), seen from the right",
                      fontsize="medium")
    profile.set_xlabel("z (forward) [m]")
    profile.set_ylabel("y (up) [m]")
    profile.xaxis.set_major_locator(MaxNLocator(4))
    profile.yaxis.set_major_locator(MaxNLocator(6))
    if both.any():
        profile.legend(loc="best", fontsize="small", markerscale=2)
    moved_mm = 1e3 * (np.linalg.norm(corrected, axis=1) - np.linalg.norm(raw, axis=1))
    change.axvline(0.0, color="#c8d6e5", linewidth=1)
    change.plot(moved_mm, corrected[:, 1], ".", color="#2e86de", markersize=3)
    change.set_ylim(extent[2:])
    change.set_title("what correction did along that column", fontsize="medium")
    change.set_xlabel("corrected minus raw range [mm]")
    change.set_ylabel("y (up) [m]")


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
    :data:`PLOTLY_JS`). At most ``limit`` points per cloud, a random sample of the finite ones (the same pixels
    for both; a stride would draw stripes). The box is to scale, no side shorter than
    :data:`POINT_CLOUD_MIN_ASPECT` of the longest (a flat wall stays a plane in view), seen from the sensor's side
    from a distance that shows all of it, and right-handed like the scan frame (+x to the scanner's left)."""
    import plotly.graph_objects as go

    keep = np.flatnonzero(np.isfinite(raw_points.reshape(-1, 3)).all(axis=1)
                          & np.isfinite(corrected_points.reshape(-1, 3)).all(axis=1))
    keep = _sample(keep, limit)
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


def _sample(pixels: np.ndarray, limit: int) -> np.ndarray:
    """At most ``limit`` of the flat ``pixels`` indices, in order: a random sample (seeded, so a report is the same
    each time), as an even stride over a grid's rows and columns keeps the same columns in every row: stripes."""
    if pixels.size <= limit:
        return pixels
    return np.sort(np.random.default_rng(0).choice(pixels, limit, replace=False))


def _scene_box(xyz: np.ndarray) -> dict[str, object]:
    """plotly's scene axes around points (n, 3) [m] in our axes (x, y up, z forward): each axis's range about
    its points, no shorter than :data:`POINT_CLOUD_MIN_ASPECT` of the longest, and the box to that scale."""
    low, high = (xyz.min(axis=0), xyz.max(axis=0)) if xyz.size else (np.zeros(3), np.ones(3))
    spans = np.maximum(high - low, POINT_CLOUD_MIN_ASPECT * max(float((high - low).max()), 1e-3))
    centre, ratio = 0.5 * (low + high), spans / spans.max()
    scene: dict[str, object] = {"aspectmode": "manual"}
    for ours, theirs, title in ((0, "x", "x (left) [m]"), (2, "y", "z (forward) [m]"), (1, "z", "y (up) [m]")):
        half = 0.5 * float(spans[ours])  # plotly's z is up: our y
        bounds = [float(centre[ours]) - half, float(centre[ours]) + half]
        # Our (x, z, y) in plotly's right-handed (x, y, z) would mirror the scene: x runs the other way round.
        scene[f"{theirs}axis"] = {"title": {"text": title}, "range": bounds[::-1] if ours == 0 else bounds}
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
