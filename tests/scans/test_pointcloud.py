"""LAS 1.4 / LAZ and PLY point clouds, each opened by the library LiDAR tools read them with (laspy, plyfile)."""

from __future__ import annotations

import laspy
import numpy as np
import pytest
from plyfile import PlyData

from mpi_lidar.scans.geometry import point_cloud
from mpi_lidar.scans.pointcloud import (
    LAS_SCALE_M,
    POINT_CLOUD_FORMATS,
    correction_fields,
    write_las,
    write_ply,
    write_point_cloud,
)
from tests.scan_factory import two_path_scan


@pytest.fixture
def cloud():
    """Points and fields of a small scan whose pixel (3, 5) is invalid (NaN), as after a correction."""
    scan = two_path_scan("cloud", height=6, width=8)
    corrected = scan.depth[-1] - 0.004
    corrected[3, 5] = np.nan
    flags = np.ones(scan.shape, np.uint8)
    flags[:, :4], flags[3, 5] = 0, 2
    points = point_cloud(corrected, scan.rays())
    return points, correction_fields(scan.depth[-1], corrected, flags, scan.amplitude[-1])


def _expected(points):
    keep = np.isfinite(points).all(axis=-1)
    rows, columns = np.nonzero(keep)
    return keep, rows, columns


@pytest.mark.parametrize("suffix", ["las", "laz"])
def test_write_las__laspy_reads_points_and_every_field(tmp_path, cloud, suffix):
    points, fields = cloud
    path = write_las(tmp_path / f"scan.{suffix}", points, fields)
    keep, rows, columns = _expected(points)
    las = laspy.read(path)
    assert las.header.version == laspy.header.Version(1, 4)
    assert las.header.are_points_compressed == (suffix == "laz")
    assert las.header.point_count == keep.sum() == points.shape[0] * points.shape[1] - 1
    np.testing.assert_allclose(las.header.scales, LAS_SCALE_M)
    xyz = np.stack([las.x, las.y, las.z], axis=1)
    np.testing.assert_allclose(xyz, points[keep], atol=LAS_SCALE_M / 2 + 1e-9)
    assert set(las.point_format.extra_dimension_names) == {"raw_range_m", "corrected_range_m", "correction_mm",
                                                           "flag", "amplitude_v2", "row", "column"}
    np.testing.assert_array_equal(las.row, rows)
    np.testing.assert_array_equal(las.column, columns)
    assert las.row.dtype == np.uint32 and las.flag.dtype == np.uint8
    for name in ("raw_range_m", "corrected_range_m", "correction_mm", "flag", "amplitude_v2"):
        np.testing.assert_array_equal(np.asarray(las[name]), fields[name][keep], err_msg=name)
    np.testing.assert_allclose(las.correction_mm, -4.0, atol=1e-3)
    descriptions = {p.name: p.description for p in las.point_format.extra_dimensions}
    assert descriptions["raw_range_m"] == "raw range [m]" and descriptions["amplitude_v2"] == "amplitude [V^2]"


def test_write_ply__plyfile_reads_named_fields(tmp_path, cloud):
    points, fields = cloud
    path = write_ply(tmp_path / "scan.ply", points, fields)
    keep, rows, columns = _expected(points)
    ply = PlyData.read(str(path))
    assert not ply.text and ply.byte_order == "<"
    vertex = ply["vertex"]
    assert [p.name for p in vertex.properties] == ["x", "y", "z", "raw_range_m", "corrected_range_m",
                                                   "correction_mm", "flag", "amplitude_v2", "row", "column"]
    np.testing.assert_allclose(np.stack([vertex["x"], vertex["y"], vertex["z"]], axis=1), points[keep], rtol=1e-6)
    np.testing.assert_array_equal(vertex["row"], rows)
    np.testing.assert_array_equal(vertex["column"], columns)
    for name in ("raw_range_m", "corrected_range_m", "correction_mm", "flag", "amplitude_v2"):
        np.testing.assert_array_equal(vertex[name], fields[name][keep], err_msg=name)


@pytest.mark.parametrize("fmt", POINT_CLOUD_FORMATS)
def test_write_point_cloud__format_decides_and_replaces_atomically(tmp_path, cloud, fmt):
    points, fields = cloud
    path = tmp_path / f"out.{fmt}"
    path.write_bytes(b"old")
    assert write_point_cloud(path, fmt, points, fields) == path
    assert sorted(p.name for p in tmp_path.iterdir()) == [path.name], "no staging file left"
    if fmt == "ply":
        assert PlyData.read(str(path))["vertex"].count == np.isfinite(points).all(axis=-1).sum()
    else:
        assert laspy.read(path).header.are_points_compressed == (fmt == "laz")


def test_write_las__laz_by_suffix_and_empty_cloud(tmp_path):
    nan = np.full((2, 3, 3), np.nan)
    path = write_las(tmp_path / "empty.laz", nan, {"flag": np.full((2, 3), 2, np.uint8)})
    las = laspy.read(path)
    assert las.header.are_points_compressed and las.header.point_count == 0


@pytest.mark.parametrize(("points", "fields", "message"), [
    (np.zeros((2, 3)), {}, r"shape \(H, W, 3\)"),
    (np.zeros((2, 3, 3)), {"flag": np.zeros((3, 2))}, "must have shape"),
    (np.zeros((2, 3, 3)), {"row": np.zeros((2, 3))}, "reserved"),
    (np.zeros((2, 3, 3)), {"name": np.full((2, 3), "a")}, "numeric"),
])
def test_point_cloud_writers__bad_inputs_are_refused_before_writing(tmp_path, points, fields, message):
    for fmt in POINT_CLOUD_FORMATS:
        with pytest.raises(ValueError, match=message):
            write_point_cloud(tmp_path / f"bad.{fmt}", fmt, points, fields)
    with pytest.raises(ValueError, match="unknown point cloud format"):
        write_point_cloud(tmp_path / "bad.xyz", "xyz", np.zeros((2, 3, 3)), {})
    assert not any(tmp_path.iterdir())
