"""Figures of a corrected scan: the maps, the rasterized point-cloud views and the 3-D view."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from mpi_lidar.correction import Correction, CorrectionOptions, Flag
from mpi_lidar.physics.coupling import DEFAULT_FOOTPRINT_AREA_M2
from mpi_lidar.reporting.figures import (
    VIEW_3D_POINTS,
    _mean_raster,
    maps_figure,
    point_cloud_figure,
    point_cloud_view_3d,
)
from mpi_lidar.reporting.metrics import applied_correction_mm
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


def test_point_cloud_figure__images_not_markers_for_a_million_points():
    points = np.random.default_rng(0).normal(size=(1000, 1000, 3)) + np.array([0.0, 0.0, 2.0])
    points[0, :10] = np.nan  # invalid pixels are left out, not drawn at the origin
    fig = point_cloud_figure(points, points + 0.01)
    views = [ax for ax in fig.axes if ax.get_title()]
    assert len(views) == 4
    assert all(len(ax.collections) == 0 and len(ax.images) == 1 for ax in views)
    assert "999,990 points" in fig.axes[0].get_title()


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
    assert {round(bottom), round(top)} == {round(np.degrees(0.15)), round(np.degrees(-0.15))}
    applied = applied_correction_mm(scan, correction)
    corrected = correction.flags == Flag.CORRECTED
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
    top, side = fig.axes[0], fig.axes[2]
    for ax in (top, side):
        left, right, bottom, up = ax.images[0].get_extent()
        assert 0.5 - 1e-9 <= min(right - left, up - bottom) / max(right - left, up - bottom) <= 1.0
        assert ax.get_aspect() == 1.0  # to scale: the box is widened, never stretched
        assert 3 <= len(ax.get_xticks()) <= 8 and 3 <= len(ax.get_yticks()) <= 8
        assert np.isfinite(ax.images[0].get_array()).any()
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
