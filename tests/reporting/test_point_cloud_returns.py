"""Pixels resolved into two returns in the point clouds: two points each, LAS return 1 and 2 of 2 (the nearer
first), the header's counts by return and bounds those of every point, and a second vertex in the PLY."""

from __future__ import annotations

import laspy
import numpy as np
import pytest
from plyfile import PlyData

from mpi_lidar.correction import Correction
from mpi_lidar.correction.mixed import SecondReturns
from mpi_lidar.correction.options import Flag
from mpi_lidar.reporting.point_cloud_files import TWO_RETURNS_RECORD, write_point_clouds
from mpi_lidar.scans.pointcloud import PointCloudFormat, las_metadata
from tests.scan_factory import two_path_scan

pytestmark = pytest.mark.unit

H, W = 10, 12
# (row, column): the second return's range [m] and share; the first lies behind its pixel's, the second before.
RESOLVED = {(2, 3): (9.0, 0.3), (7, 8): (0.9, 0.25), (5, 11): (6.5, 0.45)}


SECOND_SIGMA_M = 0.031  # the second returns' own 1-sigma, unlike every first return's 0.002 m


def _corrected(resolved: bool = True):
    """A scan's correction with one mixed pixel (withheld) and, when ``resolved``, the pixels of :data:`RESOLVED`."""
    scan = two_path_scan("returns", height=H, width=W)
    measured = scan.depth[-1].copy()
    flags = np.full((H, W), Flag.NO_MULTIPATH, np.uint8)
    depth = measured.astype(np.float32).copy()
    flags[4, 4], depth[4, 4] = Flag.MIXED, np.nan
    second = None
    if resolved:
        ranges, shares = np.full((H, W), np.nan, np.float32), np.full((H, W), np.nan, np.float32)
        for (row, column), (second_m, share) in RESOLVED.items():
            flags[row, column] = Flag.TWO_RETURNS
            ranges[row, column], shares[row, column] = second_m, share
        sigmas = np.where(np.isfinite(ranges), SECOND_SIGMA_M, np.nan).astype(np.float32)
        second = SecondReturns(ranges, shares, sigmas)
    correction = Correction(depth=depth, flags=flags, measured_depth=measured,
                            uncertainty_m=np.full((H, W), 0.002, np.float32), second_returns=second)
    return scan, correction


def _ranges(las) -> np.ndarray:
    return np.linalg.norm(np.stack([las.x, las.y, las.z], axis=1), axis=1)


@pytest.mark.parametrize("fmt", [PointCloudFormat.LAZ, PointCloudFormat.LAS])
def test_write_point_clouds__resolved_pixels_are_returns_one_and_two_of_two(tmp_path, fmt):
    scan, correction = _corrected()
    write_point_clouds(tmp_path, (fmt,), scan.rays(), scan, correction)
    las = laspy.read(tmp_path / f"corrected.{fmt}")
    rows, columns = np.asarray(las.row), np.asarray(las.column)
    numbers, counts = np.asarray(las.return_number), np.asarray(las.number_of_returns)
    ranges = _ranges(las)
    # every pixel but the resolved ones is one point, return 1 of 1; the mixed one is withheld as before
    assert las.header.point_count == H * W + len(RESOLVED)
    single = np.ones(len(rows), bool)
    for (row, column), (second_m, share) in RESOLVED.items():
        at = np.flatnonzero((rows == row) & (columns == column))
        assert at.size == 2 and (counts[at] == 2).all() and sorted(numbers[at]) == [1, 2]
        nearer, farther = at[np.argsort(ranges[at])]
        assert numbers[nearer] == 1 and numbers[farther] == 2, "returns numbered by range, the nearer first"
        np.testing.assert_allclose(sorted(ranges[at]), sorted([second_m, correction.depth[row, column]]), atol=2e-4)
        np.testing.assert_allclose(np.asarray(las.corrected_range_m)[at], ranges[at], atol=2e-4)
        second_point = at[np.argmin(np.abs(ranges[at] - second_m))]
        np.testing.assert_allclose(np.asarray(las.return_share)[at].sum(), 1.0, atol=1e-6)
        np.testing.assert_allclose(np.asarray(las.return_share)[second_point], share, atol=1e-6)
        assert np.asarray(las.uncertainty_m)[second_point] == pytest.approx(SECOND_SIGMA_M), "its own sigma"
        assert (np.asarray(las.flag)[at] == Flag.TWO_RETURNS).all() and not np.asarray(las.withheld)[at].any()
        single[at] = False
    assert (numbers[single] == 1).all() and (counts[single] == 1).all()
    np.testing.assert_array_equal(np.asarray(las.return_share)[single], 1.0)
    # the header: points by return, and bounds that hold the second returns (one lies 9 m out)
    assert list(las.header.number_of_points_by_return[:3]) == [H * W, len(RESOLVED), 0]
    xyz = np.stack([las.x, las.y, las.z], axis=1)
    np.testing.assert_allclose(las.header.mins, xyz.min(0), atol=1e-4)
    np.testing.assert_allclose(las.header.maxs, xyz.max(0), atol=1e-4)
    assert ranges.max() > 8.9
    assert las_metadata(tmp_path / f"corrected.{fmt}")["returns"] == TWO_RETURNS_RECORD
    assert "return_number" not in las.point_format.extra_dimension_names, "held in the return bits"


def test_write_point_clouds__without_resolved_pixels_every_point_one_of_one_and_no_new_field(tmp_path):
    scan, correction = _corrected(resolved=False)
    write_point_clouds(tmp_path, (PointCloudFormat.LAZ, PointCloudFormat.PLY), scan.rays(), scan, correction)
    las = laspy.read(tmp_path / "corrected.laz")
    assert (np.asarray(las.return_number) == 1).all() and (np.asarray(las.number_of_returns) == 1).all()
    assert "return_share" not in las.point_format.extra_dimension_names
    assert "returns" not in las_metadata(tmp_path / "corrected.laz")
    names = [p.name for p in PlyData.read(str(tmp_path / "corrected.ply"))["vertex"].properties]
    assert not {"scalar_return_number", "scalar_return_share"} & set(names)


def test_write_point_clouds__ply_second_returns_are_vertices_of_their_own(tmp_path):
    scan, correction = _corrected()
    write_point_clouds(tmp_path, (PointCloudFormat.PLY,), scan.rays(), scan, correction)
    corrected = PlyData.read(str(tmp_path / "corrected.ply"))["vertex"]
    raw = PlyData.read(str(tmp_path / "raw.ply"))["vertex"]
    valid = int(np.isfinite(correction.depth).sum())
    assert raw.count == valid and corrected.count == valid + len(RESOLVED)
    assert "scalar_return_number" not in [p.name for p in raw.properties], "the raw cloud has one return a pixel"
    ranges = np.linalg.norm(np.stack([corrected["x"], corrected["y"], corrected["z"]], axis=1), axis=1)
    for (row, column), (second_m, _) in RESOLVED.items():
        at = np.flatnonzero((corrected["scalar_row"] == row) & (corrected["scalar_column"] == column))
        assert at.size == 2 and sorted(corrected["scalar_return_number"][at]) == [1, 2]
        assert (corrected["scalar_number_of_returns"][at] == 2).all()
        assert np.isclose(ranges[at], second_m, atol=1e-4).sum() == 1
        for colour in ("red", "green", "blue"):  # coloured as their pixel
            assert corrected[colour][at[0]] == corrected[colour][at[1]]
