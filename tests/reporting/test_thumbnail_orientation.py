"""The thumbnail and the maps are drawn the same way round: seen from behind the scanner, an object at positive
azimuth (+x, the scanner's left) on the left, whichever way the scan's columns run and however its geometry is
given."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from mpi_lidar.correction import Correction, Flag
from mpi_lidar.reporting.figures import PIXEL_COLUMNS, PIXEL_COLUMNS_ORIENTED, maps_figure
from mpi_lidar.reporting.thumbnail import FLAG_COLOURS, THUMBNAIL_GAP_PX, azimuth_rises, thumbnail_image
from mpi_lidar.scans.scan import grid_rays
from tests.scan_factory import two_path_scan

pytestmark = pytest.mark.unit

CORRECTED_RGB = tuple(int(FLAG_COLOURS[Flag.CORRECTED][i:i + 2], 16) for i in (1, 3, 5))


def _scans():
    rising = two_path_scan("rising", height=6, width=16)
    falling = replace(rising, azimuth_rad=np.asarray(rising.azimuth_rad)[::-1].copy())
    rays = {f"rays of a {way} grid": replace(rising, azimuth_rad=None, elevation_rad=None,
                                              ray_directions=grid_rays(grid.azimuth_rad, grid.elevation_rad))
            for way, grid in (("rising", rising), ("falling", falling))}
    return {"azimuth rising": rising, "azimuth falling": falling, **rays}


def _object_on_the_left(scan):
    """The columns whose rays point to the scanner's left (x > 0), and a correction that flags them corrected."""
    left = scan.rays()[0, :, 0] > 0.05
    flags = np.full(scan.shape, Flag.NO_MULTIPATH, np.uint8)
    flags[:, left] = Flag.CORRECTED
    return left, Correction(depth=np.full(scan.shape, 2.0, np.float32), flags=flags)


@pytest.mark.parametrize("case", list(_scans()))
def test_thumbnail_image__an_object_at_positive_azimuth_is_on_the_left(case):
    scan = _scans()[case]
    _, correction = _object_on_the_left(scan)
    image, _ = thumbnail_image(correction, mirror=azimuth_rises(scan))
    panel = (image.shape[1] - THUMBNAIL_GAP_PX) // 2
    flag_panel = image[image.shape[0] // 2, panel + THUMBNAIL_GAP_PX:]
    shown = np.flatnonzero((flag_panel == CORRECTED_RGB).all(axis=1))
    assert shown.size > 0 and shown.max() < panel // 2, f"{case}: the object is drawn on the right"


def _share_from_the_left(ax, column: int, width: int) -> float:
    """Where the middle of ``column`` of a map of ``width`` columns is drawn, as a share of the axes' width from
    its left edge: from the image's extent (its data coordinates) and the axis limits (their direction)."""
    left, right = ax.images[0].get_extent()[:2]
    x = left + (column + 0.5) * (right - left) / width
    low, high = ax.get_xlim()
    return (x - low) / (high - low)


@pytest.mark.parametrize("case", list(_scans()))
def test_maps_figure__an_object_at_positive_azimuth_is_on_the_left_as_on_the_thumbnail(case):
    scan = _scans()[case]
    left, correction = _object_on_the_left(scan)
    fig = maps_figure(scan, correction)
    flag_map = next(ax for ax in fig.axes if ax.get_title() == "what was done\nper pixel")
    assert (flag_map.images[0].get_array() == correction.flags).all(), "the map draws the scan's own columns"
    shown = [_share_from_the_left(flag_map, column, scan.shape[1]) for column in np.flatnonzero(left)]
    assert max(shown) < 0.5, f"{case}: the object is drawn on the right of the map"
    if scan.azimuth_rad is None:  # pixel columns: they run right to left exactly where the azimuth rises
        assert flag_map.get_xlabel() == PIXEL_COLUMNS_ORIENTED
        assert (flag_map.get_xlim()[0] > flag_map.get_xlim()[1]) == azimuth_rises(scan)


def test_maps_figure__without_geometry_the_columns_run_left_to_right():
    scan = replace(_scans()["azimuth rising"], azimuth_rad=None, elevation_rad=None)
    fig = maps_figure(scan, Correction(depth=np.full(scan.shape, 2.0, np.float32),
                                       flags=np.full(scan.shape, Flag.NO_MULTIPATH, np.uint8)))
    flag_map = next(ax for ax in fig.axes if ax.get_title() == "what was done\nper pixel")
    assert flag_map.get_xlabel() == PIXEL_COLUMNS
    assert flag_map.get_xlim()[0] < flag_map.get_xlim()[1]
