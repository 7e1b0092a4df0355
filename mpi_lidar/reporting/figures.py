"""Figures of a corrected scan at level full: the maps, the point-cloud views and the interactive 3-D view.

Every figure is a :class:`matplotlib.figure.Figure` of its own, drawn without pyplot: nothing of pyplot's
global state (its backend, its open figures) is touched, and ``Figure.savefig`` renders with the Agg canvas.
"""

from __future__ import annotations

import os
from collections.abc import Callable
from dataclasses import dataclass
from functools import partial
from pathlib import Path
from typing import NamedTuple

import numpy as np
from matplotlib.axes import Axes
from matplotlib.colors import ListedColormap
from matplotlib.figure import Figure
from matplotlib.layout_engine import ConstrainedLayoutEngine
from matplotlib.patches import Patch
from matplotlib.ticker import MaxNLocator
from matplotlib.transforms import ScaledTranslation

from mpi_lidar.correction import Correction, Flag, UnservedReason
from mpi_lidar.reporting.metrics import amplitude_v2, applied_correction_mm, measured_depth
from mpi_lidar.reporting.thumbnail import FLAG_COLOURS, azimuth_rises
from mpi_lidar.scans.scan import Scan
from mpi_lidar.storage.atomic import atomic_path

VIEW_3D_POINTS = 20_000  # most points per cloud in the interactive 3-D view of report.html
PLOTLY_JS = "plotly.min.js"
VIEW_3D_FALLBACK = "interactive 3-D view: open report.html"


class MapAxes(NamedTuple):
    """How a map of the scan grid is drawn: the ``extent`` of ``imshow`` (None: pixel indices), the axis labels, and
    whether the x axis runs from high to low values (``reversed_x``)."""

    extent: tuple[float, float, float, float] | None
    xlabel: str
    ylabel: str
    reversed_x: bool


PIXEL_COLUMNS = "column [pixel]"
PIXEL_COLUMNS_ORIENTED = "column [pixel] (azimuth grows leftwards)"


def grid_axes(scan: Scan) -> MapAxes:
    """The axes of a map of the scan grid: azimuth and elevation [deg] where the scan has an azimuth/elevation grid,
    pixel indices otherwise (extent None). Either way the larger azimuth is on the left (the scanner's left, seen
    from behind it, as the thumbnail shows it): an axis in degrees runs high to low, and so does one of pixel
    columns where the azimuth grows along the columns (a scan given as ray directions alone). A scan without any
    geometry keeps its columns left to right, as nothing says which way it runs."""
    h, w = scan.shape
    az, el = scan.azimuth_rad, scan.elevation_rad
    if az is None or el is None or np.size(az) != w or np.size(el) != h:
        rises = azimuth_rises(scan)
        columns = PIXEL_COLUMNS_ORIENTED if rises or scan.has_geometry else PIXEL_COLUMNS
        return MapAxes(None, columns, "row [pixel]", rises)
    az, el = np.degrees(np.asarray(az, dtype=np.float64)), np.degrees(np.asarray(el, dtype=np.float64))
    half_az = 0.5 * (az[-1] - az[0]) / (w - 1) if w > 1 else 0.05
    half_el = 0.5 * (el[-1] - el[0]) / (h - 1) if h > 1 else 0.05
    # imshow draws row 0 at the top: the top edge is the first row's elevation.
    extent = (float(az[0] - half_az), float(az[-1] + half_az), float(el[-1] + half_el), float(el[0] - half_el))
    return MapAxes(extent, "azimuth [deg]", "elevation [deg]", True)


MAPS_PAGE_IN = 9.6  # width of maps.png [in]: the report page's (about 1150 pixels at 120 dpi)
MAP_MIN_IN, MAP_MAX_IN = 0.9, 3.4  # a map's height on the page: never a strip, never a tower [in]
MAP_MIN_WIDTH_IN = 2.6  # a map's least width on the page, where it is not tall [in]
WIDE_MAP = 0.5  # height over width below which a map takes its colour bar under it, not beside it
COLOUR_BAR_IN = 0.8  # a colour bar beside a map, with its tick labels [in]


@dataclass(frozen=True)
class MapLayout:
    """How the panels of maps.png sit on the page: ``columns`` per row, each map ``map_in`` (width, height) [in],
    the colour bars under the maps (``wide``) or beside them, and the figure's size [in]."""

    columns: int
    rows: int
    map_in: tuple[float, float]
    wide: bool
    figsize: tuple[float, float]


def map_layout(aspect: float, panels: int, page_in: float = MAPS_PAGE_IN) -> MapLayout:
    """The layout of ``panels`` maps of ``aspect`` (height over width, as drawn) on a page ``page_in`` wide [in]:
    the most columns that keep each map at least :data:`MAP_MIN_IN` high and :data:`MAP_MIN_WIDTH_IN` wide (or as
    large as :data:`MAP_MAX_IN` allows a tall one), the figure as tall as its rows need: a wide scan's maps run the
    page's width with their colour bars under them, proportionate to them."""
    wide = aspect < WIDE_MAP
    beside = 0.7 + (0.0 if wide else COLOUR_BAR_IN)  # the y label and ticks, and a colour bar beside the map [in]
    around = 0.95 + (0.45 if wide else 0.0)  # the title (two lines), x label and ticks, a colour bar under it [in]
    tallest = MAP_MAX_IN / aspect  # the widest a map may be before it is taller than MAP_MAX_IN [in]
    for columns in (4, 3, 2, 1):
        width = page_in / columns - beside
        if width >= tallest or (width >= MAP_MIN_WIDTH_IN and aspect * width >= MAP_MIN_IN):
            break
    width = min(width, tallest)
    rows = -(-panels // columns)
    return MapLayout(columns, rows, (width, aspect * width), wide,
                     (page_in, rows * (aspect * width + around) + 0.45))


def map_aspect(scan: Scan) -> float:
    """A map's height over its width as drawn: to scale in degrees where the scan has that grid, else square
    pixels."""
    extent = grid_axes(scan).extent
    h, w = scan.shape
    if extent is None:
        return h / max(w, 1)
    return abs(extent[3] - extent[2]) / max(abs(extent[1] - extent[0]), 1e-9)


def amplitude_shown(scan: Scan, correction: Correction) -> tuple[np.ndarray, str]:
    """The highest frequency's amplitude as the maps show it and its unit: V^2 where the unit is known to be V^2
    (given, or assumed with nothing against it: ``V^2, assumed``), the scan's own values in ``scan units`` where
    the scan's evidence contradicts the unit or the model could not serve it for its amplitude unit."""
    reading = correction.reading
    unit_doubted = (reading is not None and not reading.unit_trusted) or (
        correction.unserved is not None and correction.unserved.reason == UnservedReason.AMPLITUDE_UNITS)
    if unit_doubted:
        return np.asarray(scan.amplitude[-1], dtype=np.float32), "scan units"
    assumed = reading is not None and not reading.unit_given
    return amplitude_v2(scan, correction), "V$^2$, assumed" if assumed else "V$^2$"


def maps_figure(scan: Scan, correction: Correction) -> Figure:
    """Raw and corrected depth, amplitude, what correction did and the flag map; with a reference depth also
    the error maps before and after (Fig. 7/8 b-f).

    Without a reference (every archived scan) the panels after the amplitude show the applied correction
    (corrected minus raw depth, where corrected), the geometry gate's expected multipath bias and the flags;
    with one, the error maps come before the bias. Axes in degrees of azimuth and elevation where the scan has
    that grid (to scale, the scanner's left on the left: azimuth grows leftwards, as the scan frame has it seen
    from behind the scanner), pixel indices otherwise, the same way round where the scan's geometry says which
    way its azimuth runs (:func:`grid_axes`). The figure is sized by the maps' shape
    (:func:`map_layout`): a wide scan's maps run the page's width with their colour bars under them.
    """
    grid = grid_axes(scan)
    panels = _map_panels(scan, correction)
    layout = map_layout(map_aspect(scan), len(panels))
    # Beside the maps, room between the columns for their colour bars (the layout does not see them).
    between = 0.02 if layout.wide else COLOUR_BAR_IN * (layout.columns - 1) / layout.figsize[0]
    fig = Figure(figsize=layout.figsize, layout=ConstrainedLayoutEngine(wspace=between))
    axes = fig.subplots(layout.rows, layout.columns, squeeze=False).ravel()
    for ax, draw in zip(axes, panels, strict=False):
        draw(ax, grid, layout.wide)
    for ax in axes[len(panels):]:
        ax.remove()
    fig.suptitle(f"scan {scan.name}")
    return fig


MapPanel = Callable[[Axes, MapAxes, bool], None]


def _map_panels(scan: Scan, correction: Correction) -> list[MapPanel]:
    """What maps.png draws, panel by panel, in order."""
    label = f"{scan.frequencies_hz[-1] / 1e6:g} MHz"
    raw_depth = measured_depth(scan, correction)
    limits = _depth_limits(correction.depth, raw_depth)
    amplitude, unit = amplitude_shown(scan, correction)
    panels: list[MapPanel] = [
        partial(_image, values=raw_depth, title=f"raw depth {label} [m]", cmap="viridis", limits=limits),
        (partial(_image, values=correction.depth, title="corrected depth [m]", cmap="viridis", limits=limits)
         if np.isfinite(correction.depth).any() else
         partial(_words, text="corrected depth:\nno pixel has one\n(every pixel invalid)")),
        partial(_image, values=amplitude, title=f"amplitude {label} [{unit}]", cmap="magma", limits=None),
        _applied_panel(scan, correction)]
    if scan.reference_depth is not None:
        raw_error = 1e3 * (raw_depth - scan.reference_depth)
        corrected_error = 1e3 * (correction.depth - scan.reference_depth)
        valid = np.isfinite(corrected_error)
        span = float(np.quantile(np.abs(raw_error[valid]), 0.99)) if valid.any() else 1.0
        raw_error[~valid] = np.nan
        panels += [partial(_image, values=raw_error, title="raw error [mm]", cmap="RdBu_r", limits=(-span, span)),
                   partial(_image, values=corrected_error, title="corrected error [mm]", cmap="RdBu_r",
                           limits=(-span, span))]
    if correction.multipath_bias_m is not None:
        bias = 1e3 * np.asarray(correction.multipath_bias_m, dtype=np.float64)
        finite_bias = bias[np.isfinite(bias)]
        top = max(float(np.quantile(finite_bias, 0.99)), 1e-3) if finite_bias.size else 1.0
        panels.append(partial(_image, values=bias, title="expected multipath\nbias [mm]", cmap="cividis",
                              limits=(0.0, top)))
    else:
        panels.append(partial(_words, text="expected multipath bias:\ncomputed by the geometry gate only"))
    return [*panels, partial(_flag_map, flags=correction.flags)]


def _depth_limits(corrected: np.ndarray, raw: np.ndarray) -> tuple[float, float]:
    """The depth maps' colour limits [m]: the 1 and 99 % quantiles of the corrected depths, of the raw ones where
    no pixel has a corrected depth (an unserved or wholly invalid scan still shows what it measured)."""
    for values in (raw[np.isfinite(corrected)], raw[np.isfinite(raw)]):
        if values.size:
            low, high = np.quantile(values, [0.01, 0.99])
            return float(low), float(max(high, low + 1e-3))
    return 0.0, 1.0


def _applied_panel(scan: Scan, correction: Correction) -> MapPanel:
    applied = applied_correction_mm(scan, correction)
    shown = np.abs(applied[np.isfinite(applied)])
    if not shown.size:
        return partial(_words, text="applied correction:\nno pixel was corrected")
    span = max(float(np.quantile(shown, 0.99)), 1e-3)
    return partial(_image, values=applied, title=f"applied correction [mm]\n({shown.size:,} pixels corrected)",
                   cmap="RdBu_r", limits=(-span, span))


def _words(ax: Axes, grid: object = None, wide: bool = False, *, text: str) -> None:
    """A panel that has nothing to draw says why in words."""
    ax.text(0.5, 0.5, text, ha="center", va="center", transform=ax.transAxes)
    ax.set_axis_off()


def _axes_of_map(ax: Axes, title: str, grid: MapAxes) -> None:
    ax.set_title(title, fontsize="medium")
    ax.set_xlabel(grid.xlabel)
    ax.set_ylabel(grid.ylabel)
    if grid.reversed_x:  # azimuth grows to the scanner's left: larger azimuths on the left, as seen from it
        low, high = sorted(ax.get_xlim())
        ax.set_xlim(high, low)


def _image(ax: Axes, grid: MapAxes, wide: bool, *, values: np.ndarray, title: str, cmap: str,
           limits: tuple[float, float] | None) -> None:
    shown = ax.imshow(values, cmap=cmap, vmin=None if limits is None else limits[0],
                      vmax=None if limits is None else limits[1], interpolation="nearest", extent=grid.extent)
    if wide:  # a bar under the map, as wide as the map: a few ticks, their labels clear of each other
        bar = ax.figure.colorbar(shown, ax=ax, location="bottom", aspect=30, pad=0.02)
        bar.ax.xaxis.set_major_locator(MaxNLocator(5))
    else:  # a bar beside the map's drawn box, as tall as the map (the layout's cell may be taller)
        ax.figure.colorbar(shown, cax=ax.inset_axes((1.04, 0.0, 0.05, 1.0)))
    _axes_of_map(ax, title, grid)


def _flag_map(ax: Axes, grid: MapAxes, wide: bool, *, flags: np.ndarray) -> None:
    """The flags in the registry's colours, a key of the flags the scan has (under a wide map, beside others)."""
    ax.imshow(flags, cmap=ListedColormap(FLAG_COLOURS), vmin=-0.5, vmax=len(Flag) - 0.5, interpolation="nearest",
              extent=grid.extent)
    present = [flag for flag in Flag if (flags == flag).any()]
    handles = [Patch(facecolor=FLAG_COLOURS[flag], edgecolor="black", linewidth=0.5,
                     label=flag.name.lower().replace("_", " ")) for flag in present]
    # Under a wide map below its x label (half an inch down, whatever the map's height), beside any other.
    below = ax.transAxes + ScaledTranslation(0.0, -0.5, ax.figure.dpi_scale_trans)
    where = ({"loc": "upper center", "bbox_to_anchor": (0.5, 0.0), "bbox_transform": below,
              "ncols": min(len(handles), 3)} if wide else {"loc": "center left", "bbox_to_anchor": (1.02, 0.5)})
    ax.legend(handles=handles, frameon=False, fontsize="small", handlelength=1.0, **where)
    _axes_of_map(ax, "what was done\nper pixel", grid)


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
