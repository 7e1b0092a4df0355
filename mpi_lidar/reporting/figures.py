"""Figures of a corrected scan at level full: the maps (the point-cloud views are
:mod:`mpi_lidar.reporting.cloud_figures`'s).

Every figure is a :class:`matplotlib.figure.Figure` of its own, drawn without pyplot: nothing of pyplot's
global state (its backend, its open figures) is touched, and ``Figure.savefig`` renders with the Agg canvas.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from functools import partial
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
