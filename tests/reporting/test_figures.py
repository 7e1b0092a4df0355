"""Figures of a corrected scan: the maps, the rasterized point-cloud views and the 3-D view."""

from __future__ import annotations

import re
from dataclasses import replace

import numpy as np
import pytest

from mpi_lidar.correction import Correction, CorrectionOptions, Flag
from mpi_lidar.physics.coupling import DEFAULT_FOOTPRINT_AREA_M2
from mpi_lidar.reporting.cloud_figures import (
    VIEW_3D_POINTS,
    _mean_raster,
    _sample,
    point_cloud_figure,
    point_cloud_view_3d,
    profile_column,
)
from mpi_lidar.reporting.figures import MAPS_PAGE_IN, map_layout, maps_figure
from mpi_lidar.reporting.metrics import applied_correction_mm
from mpi_lidar.scans import geometry
from tests.scan_factory import two_path_scan

pytestmark = pytest.mark.unit


def test_mean_raster__mean_per_cell_and_nan_where_empty():
    u = np.array([0.1, 0.1, 0.9, 0.5])
    v = np.array([0.1, 0.1, 0.9, 0.1])
    value = np.array([1.0, 3.0, 5.0, 7.0])
    image = _mean_raster(u, v, value, (0.0, 1.0, 0.0, 1.0), bins=2)
    assert image[0, 0] == 2.0  # rows along v, columns along u: both points of the lower-left cell
    assert image[0, 1] == 7.0
    assert image[1, 1] == 5.0
    assert np.isnan(image[1, 0])


def test_point_cloud_figure__top_views_are_images_the_side_profile_one_column():
    points = np.random.default_rng(0).normal(size=(1000, 1000, 3)) + np.array([0.0, 0.0, 2.0])
    points[0, :10] = np.nan  # invalid pixels are left out, not drawn at the origin
    fig = point_cloud_figure(points, points + 0.01)
    top = [ax for ax in fig.axes if "top view" in ax.get_title()]
    assert len(top) == 2 and all(len(ax.collections) == 0 and len(ax.images) == 1 for ax in top)
    assert "999,990 points" in top[0].get_title()
    profile = next(ax for ax in fig.axes if ax.get_title().startswith("side profile"))
    assert "column 500 (1,000 points)" in profile.get_title()
    assert [line.get_xdata().size for line in profile.get_lines()] == [1000, 1000]  # raw, corrected: one column


def test_profile_column__the_middle_or_the_nearest_with_the_most_points():
    grid = np.zeros((6, 9, 3))
    assert profile_column(grid, grid) == 4
    grid[:, 3:6] = np.nan
    grid[:1, 2] = np.nan  # columns 0, 1, 6 and 8 keep every point; 6 is the nearest to the middle
    assert profile_column(grid, grid) == 6
    assert profile_column(np.full_like(grid, np.nan), grid) == 4  # nothing anywhere: the middle


def test_maps_figure__archived_scan_shows_what_correction_did_in_degrees(model_dir, archived):
    from mpi_lidar import correct_scan, load_model

    scan = archived[0]
    options = CorrectionOptions(gate="geometry", min_multipath_bias_m=0.0, footprint_area_m2=DEFAULT_FOOTPRINT_AREA_M2)
    correction = correct_scan(scan, load_model(model_dir), options)
    assert correction.multipath_bias_m is not None
    fig = maps_figure(scan, correction)
    texts = [t.get_text() for ax in fig.axes for t in ax.texts]
    assert not any("skipped" in t for t in texts), texts
    titles = [" ".join(ax.get_title().split()) for ax in fig.axes]  # long titles wrap onto two lines
    assert any(t.startswith("applied correction [mm]") for t in titles)
    assert "expected multipath bias [mm]" in titles and "what was done per pixel" in titles
    maps = [ax for ax in fig.axes if ax.images]
    assert len(maps) == 6
    assert all(ax.get_xlabel() == "azimuth [deg]" and ax.get_ylabel() == "elevation [deg]" for ax in maps)
    left, right, bottom, top = maps[0].images[0].get_extent()
    assert left == pytest.approx(np.degrees(-0.2), abs=0.5) and right == pytest.approx(np.degrees(0.2), abs=0.5)
    assert maps[0].get_xlim()[0] > maps[0].get_xlim()[1], "azimuth grows to the left: the scanner's left"
    assert {round(bottom), round(top)} == {round(np.degrees(0.15)), round(np.degrees(-0.15))}
    applied = applied_correction_mm(scan, correction)
    corrected = np.isin(correction.flags, (Flag.CORRECTED, Flag.BEYOND_PRIOR))  # both hold the model's depth
    assert np.isnan(applied[~corrected]).all() and np.isfinite(applied[corrected]).any()
    np.testing.assert_allclose(applied[corrected], 1e3 * (correction.depth - scan.depth[-1])[corrected], rtol=1e-6)


def test_maps_figure__without_grid_pixel_indices_with_reference_the_error_maps(model_dir, archived):
    from mpi_lidar import correct_scan, load_model

    flat = replace(archived[0], azimuth_rad=None, elevation_rad=None)
    pixelwise = load_model(model_dir)
    fig = maps_figure(flat, correct_scan(flat, pixelwise, CorrectionOptions(gate="all")))
    maps = [ax for ax in fig.axes if ax.images]
    assert all(ax.get_xlabel() == "column [pixel]" and ax.get_ylabel() == "row [pixel]" for ax in maps)
    assert not any("skipped" in t.get_text() for ax in fig.axes for t in ax.texts)
    reference = two_path_scan("referenced")
    fig = maps_figure(reference, correct_scan(reference, pixelwise, CorrectionOptions(gate="all")))
    titles = [ax.get_title() for ax in fig.axes]
    assert {"raw error [mm]", "corrected error [mm]"} <= set(titles)
    assert any(t.startswith("applied correction [mm]") for t in titles)


def test_point_cloud_view_3d__decimated_to_the_limit():
    rng = np.random.default_rng(0)
    points = rng.normal(size=(300, 300, 3)) + np.array([0.0, 0.0, 3.0])
    points[0, :5] = np.nan
    markup = point_cloud_view_3d(points, points + 0.01, rng.normal(size=(300, 300)), limit=VIEW_3D_POINTS // 4)
    assert markup.lstrip().startswith("<div") and "<html" not in markup and "Plotly.newPlot" in markup
    assert f"{VIEW_3D_POINTS // 4:,} of each" in markup
    assert len(markup) < 1_000_000


def test_point_cloud_figure__flat_wall_top_view_is_a_box_not_a_line():
    """A wall 1 m wide and 2 mm deep: its top view keeps its axes to scale in a box at least half as deep as
    wide, with a few ticks per axis, and every row has its points."""
    x, y = np.meshgrid(np.linspace(-0.5, 0.5, 60), np.linspace(-0.3, 0.3, 40))
    rng = np.random.default_rng(0)
    wall = np.stack([x, y, 2.0 + 0.002 * rng.random(x.shape)], axis=-1)
    fig = point_cloud_figure(wall, wall)
    top, side = fig.axes[0], next(ax for ax in fig.axes if ax.get_title().startswith("side profile"))
    for ax in (top, side):
        left, right = sorted(ax.get_xlim())
        bottom, up = sorted(ax.get_ylim())
        assert 0.5 - 1e-9 <= min(right - left, up - bottom) / max(right - left, up - bottom) <= 1.0
        assert ax.get_aspect() == 1.0  # to scale: the box is widened, never stretched
        assert 3 <= len(ax.get_xticks()) <= 8 and 3 <= len(ax.get_yticks()) <= 8
    assert np.isfinite(top.images[0].get_array()).any()
    assert "2,400 points" in top.get_title()


def test_point_cloud_view_3d__a_flat_wall_keeps_a_box_of_sensible_proportions():
    x, y = np.meshgrid(np.linspace(-0.5, 0.5, 30), np.linspace(-0.3, 0.3, 20))
    wall = np.stack([x, y, np.full_like(x, 2.0)], axis=-1)
    html = point_cloud_view_3d(wall, wall, np.zeros(x.shape))
    assert '"aspectmode":"manual"' in html
    assert '"aspectratio":{"x":1.0,"y":0.5,"z":0.6' in html  # x widest, the wall's depth widened to half
    assert '"text":"z (forward) [m]"},"range":[1.75,2.25]' in html  # to scale: a plane mid-box


def test_maps_figure__no_corrected_pixel_says_so_instead_of_an_empty_map():
    scan = two_path_scan("untouched")
    flags = np.full(scan.shape, int(Flag.NO_MULTIPATH), np.uint8)
    fig = maps_figure(scan, Correction(depth=scan.depth[-1].copy(), flags=flags, inference_s=0.0, total_s=0.0))
    texts = [t.get_text() for ax in fig.axes for t in ax.texts]
    assert any("no pixel was corrected" in t for t in texts), texts
    assert not any(ax.get_title().startswith("applied correction") for ax in fig.axes)


def _square_pixel_scan(height: int, width: int):
    """A two-path scan whose pixels span equal angles (0.4 rad across its width)."""
    scan = two_path_scan("strip", height=height, width=width)
    half = 0.2 * height / width
    return replace(scan, elevation_rad=np.linspace(half, -half, height))


def _map_boxes(fig):
    """Drawn boxes (width, height) [in] of the maps and of the colour bars, rendered as saved."""
    fig.draw_without_rendering()
    inches = fig.dpi_scale_trans.inverted()
    maps = [ax for ax in fig.axes if ax.images and ax.get_label() != "<colorbar>"]
    bars = [ax for ax in fig.axes if ax.get_label() == "<colorbar>"]
    size = lambda ax: ax.get_window_extent().transformed(inches).size  # noqa: E731
    return [size(ax) for ax in maps], [size(ax) for ax in bars]


def test_maps_figure__a_24_by_96_scan_runs_the_page_width_with_proportionate_colour_bars():
    """Maps of a wide scan are at least half the page wide and more than an inch high (no 45-pixel strips), their
    colour bars under them no longer than the maps and a fraction of their height."""
    scan = _square_pixel_scan(24, 96)
    flags = np.full(scan.shape, int(Flag.NO_MULTIPATH), np.uint8)
    flags[:, :30] = Flag.CORRECTED
    depth = scan.depth[-1] - np.where(flags == Flag.CORRECTED, 0.005, 0.0).astype(np.float32)
    fig = maps_figure(scan, Correction(depth=depth, flags=flags, inference_s=0.0, total_s=0.0))
    maps, bars = _map_boxes(fig)
    assert fig.get_figwidth() == pytest.approx(MAPS_PAGE_IN)
    for width, height in maps:
        assert width >= 0.4 * MAPS_PAGE_IN and height >= 0.9, (width, height)
        assert height / width == pytest.approx(0.25, rel=0.05), "to scale: 24 x 96 square pixels"
    for width, height in bars:
        assert width <= max(w for w, _ in maps) + 0.01 and height <= 0.5 * min(h for _, h in maps), (width, height)


@pytest.mark.parametrize(("aspect", "columns"), [(0.25, 2), (0.75, 2), (3.0, 3), (0.02, 1)])
def test_map_layout__columns_by_the_maps_shape(aspect, columns):
    layout = map_layout(aspect, 8)
    assert layout.columns == columns
    width, height = layout.map_in
    assert height == pytest.approx(aspect * width)
    assert columns * width <= MAPS_PAGE_IN and (height >= 0.9 or columns == 1) and height <= 3.4 + 1e-9
    assert layout.wide == (aspect < 0.5)


def _object_on_the_left(height: int = 20, width: int = 40):
    """A wall 2 m away with a box 0.5 m nearer at positive azimuth only (the scanner's left), its points (H, W, 3)
    [m] and the box's pixels."""
    scan = two_path_scan("left_object", height=height, width=width)
    near = np.broadcast_to(np.asarray(scan.azimuth_rad) > 0.08, scan.shape)
    depth = np.where(near, 1.5, 2.0)
    return scan, geometry.point_cloud(depth, scan.rays()), near


def test_point_cloud_figure__an_object_at_positive_azimuth_is_on_the_left_of_the_top_view():
    """+x is the scanner's left (the scan frame, README): seen from above with forward up the page, an object at
    positive azimuth lies left of the middle."""
    _, points, near = _object_on_the_left()
    assert (points[near][:, 0] > 0).all()
    fig = point_cloud_figure(points, points)
    fig.draw_without_rendering()
    top = next(ax for ax in fig.axes if ax.get_title().startswith("raw: top view"))
    box = top.get_window_extent()
    shown = top.transData.transform(points[near][:, [0, 2]])
    assert (shown[:, 0] < box.x0 + 0.5 * box.width).all()
    assert top.get_xlim()[0] > top.get_xlim()[1]


def test_maps_figure__an_object_at_positive_azimuth_is_on_the_left_of_the_maps():
    scan, _, near = _object_on_the_left()
    flags = np.full(scan.shape, int(Flag.NO_MULTIPATH), np.uint8)
    depth = np.where(near, 1.5, 2.0).astype(np.float32)
    fig = maps_figure(replace(scan, depth=np.repeat(depth[None], 4, axis=0)),
                      Correction(depth=depth, flags=flags, inference_s=0.0, total_s=0.0))
    fig.draw_without_rendering()
    ax = next(ax for ax in fig.axes if ax.get_title().startswith("raw depth"))
    azimuth = np.degrees(np.asarray(scan.azimuth_rad)[near[0]])
    shown = ax.transData.transform(np.column_stack([azimuth, np.zeros_like(azimuth)]))
    box = ax.get_window_extent()
    assert (shown[:, 0] < box.x0 + 0.5 * box.width).all()


def test_point_cloud_view_3d__right_handed_x_runs_the_other_way():
    """plotly's axes take our (x, z, y): its x range runs high to low, so the scene is not mirrored."""
    _, points, _ = _object_on_the_left(30, 30)
    html = point_cloud_view_3d(points, points, np.zeros(points.shape[:2]))
    x_range = re.search(r'"xaxis":\{"title":\{"text":"x \(left\) \[m\]"\},"range":\[([-\d.e]+),([-\d.e]+)\]', html)
    assert x_range and float(x_range.group(1)) > float(x_range.group(2))


def test_sample__a_1000_by_1000_grid_keeps_points_in_every_column_no_stripes():
    """An even stride of 50 over a 1000 x 1000 grid keeps the same 20 columns in every row (stripes); the sample
    reaches every column, about equally, and keeps the order of the pixels."""
    kept = _sample(np.arange(1_000_000), VIEW_3D_POINTS)
    assert kept.size == VIEW_3D_POINTS and np.all(np.diff(kept) > 0)
    per_column = np.bincount(kept % 1000, minlength=1000)
    assert (per_column > 0).all() and per_column.max() < 3 * per_column.mean()
    per_row = np.bincount(kept // 1000, minlength=1000)
    assert (per_row > 0).all()
    assert np.array_equal(_sample(np.arange(10), 20), np.arange(10))


UNIT = re.compile(r"[\[(][^\])]+[\])]")


def _unlabelled(fig) -> list[str]:
    """Every axis of ``fig`` that draws something and lacks a label with a unit in brackets or parentheses; a colour
    bar's unit may be in its own label or in the title of the map it belongs to."""
    missing = []
    bar_titles = {id(image.colorbar.ax): image.axes.get_title() for ax in fig.axes for image in ax.images
                  if image.colorbar is not None}
    for ax in fig.axes:
        if not ax.axison:  # a panel of words
            continue
        if ax.get_label() == "<colorbar>":
            label = ax.get_xlabel() or ax.get_ylabel()
            if not UNIT.search(label) and not UNIT.search(bar_titles.get(id(ax), "")):
                missing.append(f"colour bar of {bar_titles.get(id(ax))!r}")
            continue
        missing += [f"{ax.get_title()!r}: {which} axis {label!r}" for which, label in
                    (("x", ax.get_xlabel()), ("y", ax.get_ylabel())) if not UNIT.search(label)]
    return missing


def test_figures__every_axis_has_a_label_with_a_unit(model_dir, archived):
    from mpi_lidar import correct_scan, load_model
    from mpi_lidar.reporting.report import error_histogram_figure

    model = load_model(model_dir)
    referenced = two_path_scan("referenced")
    figures = {"maps, archived": maps_figure(archived[0], correct_scan(archived[0], model)),
               "maps, referenced": maps_figure(referenced, correct_scan(referenced, model)),
               "maps, wide": maps_figure(*_plain(_square_pixel_scan(24, 96))),
               "point clouds": point_cloud_figure(*_object_on_the_left()[1:2] * 2),
               "error histogram": error_histogram_figure({"raw": np.arange(5.0), "corrected": np.arange(5.0)},
                                                         "depth error [mm]", "pixels (count)")}
    for name, fig in figures.items():
        assert _unlabelled(fig) == [], name


def _plain(scan):
    flags = np.full(scan.shape, int(Flag.NO_MULTIPATH), np.uint8)
    return scan, Correction(depth=scan.depth[-1].copy(), flags=flags, inference_s=0.0, total_s=0.0)


def test_maps_figure__amplitude_unit_said_as_known(model_dir):
    """V^2 where the unit is known; the scan's own values and unit ("scan units") where its evidence contradicts
    V^2; "V^2, assumed" where nothing was given and nothing contradicts it."""
    from mpi_lidar import correct_scan, load_model

    model = load_model(model_dir)
    scan = two_path_scan("volts")
    counts = replace(scan, name="counts", amplitude=scan.amplitude * 4000)
    titles = {}
    for name, s, options in (("given", scan, CorrectionOptions(amplitude_scale=1.0)), ("assumed", scan, None),
                             ("counts", counts, None)):
        correction = correct_scan(s, model, options or CorrectionOptions())
        fig = maps_figure(s, correction)
        ax = next(ax for ax in fig.axes if ax.get_title().startswith("amplitude"))
        titles[name] = (ax.get_title(), float(np.nanmax(ax.images[0].get_array())))
    assert titles["given"][0].endswith("[V$^2$]") and titles["assumed"][0].endswith("[V$^2$, assumed]")
    assert titles["counts"][0].endswith("[scan units]")
    assert titles["counts"][1] == pytest.approx(4000 * titles["given"][1], rel=1e-5)  # as the scan holds them
