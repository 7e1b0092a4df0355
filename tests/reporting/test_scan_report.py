"""Per-scan figures: the rasterized point-cloud views."""

from __future__ import annotations

import matplotlib

matplotlib.use("Agg")

import numpy as np

from mpi_lidar.reporting.scan_report import _mean_raster, point_cloud_figure


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
