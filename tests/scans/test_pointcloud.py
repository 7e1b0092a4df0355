"""LAS 1.4 / LAZ and PLY point clouds, each opened by the library LiDAR tools read them with (laspy, plyfile)."""

from __future__ import annotations

import json

import laspy
import numpy as np
import pytest
from plyfile import PlyData

from mpi_lidar.scans.geometry import point_cloud
from mpi_lidar.scans.pointcloud import (
    INTENSITY_MAX,
    INTENSITY_PER_COUNT_V2,
    LAS_CLASS_LOW_NOISE,
    LAS_CLASS_UNCLASSIFIED,
    LAS_METADATA_RECORD_ID,
    LAS_METADATA_USER_ID,
    LAS_SCALE_M,
    POINT_CLOUD_FORMATS,
    correction_fields,
    generator,
    intensity_counts,
    las_metadata,
    write_las,
    write_ply,
    write_point_cloud,
)
from tests.scan_factory import two_path_scan

pytestmark = pytest.mark.unit

FIELDS = ("raw_range_m", "corrected_range_m", "correction_mm", "flag", "amplitude_v2")


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
    assert set(las.point_format.extra_dimension_names) == {*FIELDS, "row", "column"}
    np.testing.assert_array_equal(las.row, rows)
    np.testing.assert_array_equal(las.column, columns)
    assert las.row.dtype == np.uint32 and las.flag.dtype == np.uint8
    for name in FIELDS:
        np.testing.assert_array_equal(np.asarray(las[name]), fields[name][keep], err_msg=name)
    np.testing.assert_allclose(las.correction_mm, -4.0, atol=1e-3)
    descriptions = {p.name: p.description for p in las.point_format.extra_dimensions}
    assert descriptions["raw_range_m"] == "raw range [m]" and descriptions["amplitude_v2"].startswith("amplitude [V^2]")
    assert all(len(text) <= 31 for text in descriptions.values())
    # one return each, nothing withheld, every point unclassified
    assert set(las.return_number) == {1} and set(las.number_of_returns) == {1}
    assert not np.any(las.withheld) and set(las.classification) == {LAS_CLASS_UNCLASSIFIED}


def test_write_las__intensity_is_the_amplitude_on_one_fixed_scale_recorded(tmp_path, cloud):
    points, fields = cloud
    las = laspy.read(write_las(tmp_path / "scan.laz", points, fields))
    keep = np.isfinite(points).all(axis=-1)
    amplitude = fields["amplitude_v2"][keep].astype(np.float64)
    record = las_metadata(tmp_path / "scan.laz")
    scale = record["intensity"]["per_count"]
    assert record["intensity"]["field"] == "amplitude_v2"
    assert scale == INTENSITY_PER_COUNT_V2, "one scale for every file of an archive"
    intensity = np.asarray(las.intensity)
    expected = np.clip(np.rint(amplitude / scale), 0, INTENSITY_MAX)
    np.testing.assert_array_equal(intensity, expected)
    assert intensity.min() > 0, "blank intensity is what viewers showed before"
    # twice the amplitude: twice the intensity, not the same file-relative counts
    doubled = laspy.read(write_las(tmp_path / "doubled.laz", points,
                                   {**fields, "amplitude_v2": 2 * fields["amplitude_v2"]}))
    unclipped = expected < INTENSITY_MAX / 2
    np.testing.assert_allclose(np.asarray(doubled.intensity)[unclipped], 2 * intensity[unclipped], atol=1)
    description = next(p.description for p in las.point_format.extra_dimensions if p.name == "amplitude_v2")
    assert f"{scale:.2e}" in description


def test_write_las__withheld_points_kept_as_noise(tmp_path, cloud):
    points, fields = cloud
    placed = points.copy()
    placed[3, 5] = point_cloud(fields["raw_range_m"], np.ones((6, 8, 3)) / np.sqrt(3))[3, 5]
    withheld = np.zeros((6, 8), bool)
    withheld[3, 5] = withheld[0, 0] = True
    las = laspy.read(write_las(tmp_path / "scan.laz", placed, fields, withheld=withheld))
    assert las.header.point_count == 48, "the invalid pixel's point is kept"
    assert np.asarray(las.withheld).sum() == 2
    marked = (np.asarray(las.row), np.asarray(las.column))
    assert set(zip(*(m[np.asarray(las.withheld, bool)] for m in marked), strict=True)) == {(0, 0), (3, 5)}
    assert np.array_equal(np.asarray(las.classification) == LAS_CLASS_LOW_NOISE, np.asarray(las.withheld, bool))
    with pytest.raises(ValueError, match="withheld must have shape"):
        write_las(tmp_path / "bad.laz", placed, fields, withheld=np.zeros((2, 2), bool))


def test_write_las__generator_json_record_and_descriptions(tmp_path, cloud):
    points, fields = cloud
    path = write_las(tmp_path / "scan.las", points, fields, descriptions={"flag": "0C 1N 2F"},
                     metadata={"frame": {"x": "right"}})
    las = laspy.read(path)
    assert las.header.generating_software == generator() and generator().startswith("mpi-lidar")
    records = [v for v in las.header.vlrs if v.user_id == LAS_METADATA_USER_ID]
    assert [v.record_id for v in records] == [LAS_METADATA_RECORD_ID]
    record = json.loads(bytes(records[0].record_data).decode())
    assert record == las_metadata(path)
    assert record["generator"] == generator() and record["frame"] == {"x": "right"}
    assert record["fields"]["flag"] == "0C 1N 2F" and record["fields"]["row"] == "pixel row of the scan grid"
    assert "withheld" in record
    assert {p.name: p.description for p in las.point_format.extra_dimensions}["flag"] == "0C 1N 2F"


def test_correction_fields__uncertainty_an_extra_field_when_given(tmp_path, cloud):
    points, fields = cloud
    assert "uncertainty_m" not in fields
    sigma = np.full((6, 8), 0.002, np.float32)
    with_sigma = correction_fields(fields["raw_range_m"], fields["corrected_range_m"], fields["flag"],
                                   fields["amplitude_v2"], sigma)
    las = laspy.read(write_las(tmp_path / "scan.laz", points, with_sigma))
    np.testing.assert_array_equal(las.uncertainty_m, np.float32(0.002))
    assert {p.name: p.description for p in las.point_format.extra_dimensions}["uncertainty_m"].endswith("[m]")


def test_intensity_counts__nan_negative_and_clipped():
    counts = intensity_counts(np.array([np.nan, -1.0, 1.0, 2.0, 5.0]), 2.0 / INTENSITY_MAX)
    np.testing.assert_array_equal(counts, [0, 0, 32768, INTENSITY_MAX, INTENSITY_MAX])


def test_write_ply__plyfile_reads_scalar_fields_and_colours(tmp_path, cloud):
    points, fields = cloud
    colors = np.zeros((6, 8, 3), np.uint8)
    colors[..., 0] = 200
    path = write_ply(tmp_path / "scan.ply", points, fields, colors, comments=("hello",))
    keep, rows, columns = _expected(points)
    ply = PlyData.read(str(path))
    assert not ply.text and ply.byte_order == "<"
    assert ply.comments == [f"generated by {generator()}", "hello"]
    vertex = ply["vertex"]
    assert [p.name for p in vertex.properties] == [
        "x", "y", "z", "red", "green", "blue", "scalar_raw_range_m", "scalar_corrected_range_m",
        "scalar_correction_mm", "scalar_flag", "scalar_amplitude_v2", "scalar_row", "scalar_column"]
    assert {vertex[c].dtype for c in ("red", "green", "blue")} == {np.dtype("u1")}
    assert set(vertex["red"]) == {200} and set(vertex["green"]) == {0}
    np.testing.assert_allclose(np.stack([vertex["x"], vertex["y"], vertex["z"]], axis=1), points[keep], rtol=1e-6)
    np.testing.assert_array_equal(vertex["scalar_row"], rows)
    np.testing.assert_array_equal(vertex["scalar_column"], columns)
    for name in FIELDS:
        np.testing.assert_array_equal(vertex[f"scalar_{name}"], fields[name][keep], err_msg=name)
    plain = PlyData.read(str(write_ply(tmp_path / "plain.ply", points, fields)))
    assert [p.name for p in plain["vertex"].properties][:4] == ["x", "y", "z", "scalar_raw_range_m"]
    with pytest.raises(ValueError, match="colors must be uint8"):
        write_ply(tmp_path / "bad.ply", points, fields, colors.astype(np.float32))


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


@pytest.mark.parametrize("band_pixels", [1, 8, 13, 48])
def test_write_las__written_a_band_of_rows_at_a_time_is_the_file_written_whole(tmp_path, cloud, band_pixels,
                                                                                monkeypatch):
    """Bands of one row to the whole grid (6 x 8 pixels) give the same points, fields, bounds and header."""
    from mpi_lidar.scans import pointcloud

    points, fields = cloud
    withheld = np.zeros(points.shape[:2], bool)
    withheld[0, :3] = True
    whole = laspy.read(write_las(tmp_path / "whole.laz", points, fields, withheld=withheld))
    monkeypatch.setattr(pointcloud, "LAS_BAND_PIXELS", band_pixels)
    banded = laspy.read(write_las(tmp_path / "banded.laz", points, fields, withheld=withheld))
    assert len(banded.points) == len(whole.points) == int(np.isfinite(points).all(-1).sum())
    for name in ("X", "Y", "Z", "intensity", "classification", "withheld", *FIELDS, "row", "column"):
        np.testing.assert_array_equal(np.asarray(banded[name]), np.asarray(whole[name]), err_msg=name)
    np.testing.assert_array_equal(banded.header.offsets, whole.header.offsets)
    np.testing.assert_allclose(banded.header.mins, whole.header.mins)
    np.testing.assert_allclose(banded.header.maxs, whole.header.maxs)
    assert las_metadata(tmp_path / "banded.laz") == las_metadata(tmp_path / "whole.laz")
