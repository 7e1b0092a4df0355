"""The writers' returns: LAS return bits from the return fields, a second return's points after the first's."""

from __future__ import annotations

import laspy
import numpy as np
import pytest

from mpi_lidar.scans.pointcloud import RETURN_FIELDS, write_las, write_las_bands, write_ply

pytestmark = pytest.mark.unit


def _grid(depth_m: float) -> np.ndarray:
    points = np.zeros((2, 3, 3))
    points[..., 2] = depth_m
    points[..., 0] = np.arange(3)[None, :]
    return points


def test_write_las__return_fields_fill_the_return_bits_not_extra_bytes(tmp_path):
    numbers = np.array([[1, 2, 1], [3, 1, 1]], np.uint8)
    counts = np.array([[1, 2, 1], [3, 2, 1]], np.uint8)
    fields = {"amplitude_v2": np.full((2, 3), 0.01, np.float32), "return_number": numbers,
              "number_of_returns": counts}
    las = laspy.read(write_las(tmp_path / "returns.las", _grid(2.0), fields))
    np.testing.assert_array_equal(las.return_number, numbers.ravel())
    np.testing.assert_array_equal(las.number_of_returns, counts.ravel())
    assert not set(RETURN_FIELDS) & set(las.point_format.extra_dimension_names)
    assert list(las.header.number_of_points_by_return[:4]) == [4, 1, 1, 0]


def test_write_las_bands__second_returns_follow_each_band_and_widen_the_bounds(tmp_path):
    first = {"amplitude_v2": np.full((2, 3), 0.01, np.float32)}
    second_points = np.full((2, 3, 3), np.nan)
    second_points[1, 2] = (2.0, 0.0, 7.5)

    path = write_las_bands(tmp_path / "two.laz", (2, 3), lambda rows: (_grid(2.0)[rows], first, None),
                           second=lambda rows: (second_points[rows], first, None))
    las = laspy.read(path)
    assert las.header.point_count == 7 and (np.asarray(las.row)[-1], np.asarray(las.column)[-1]) == (1, 2)
    np.testing.assert_allclose(las.header.maxs, [2.0, 0.0, 7.5], atol=1e-4)


def test_write_ply__second_returns_need_the_first_returns_fields(tmp_path):
    fields = {"flag": np.zeros((2, 3), np.uint8)}
    with pytest.raises(ValueError, match="second returns' fields"):
        write_ply(tmp_path / "bad.ply", _grid(2.0), fields, second=(_grid(5.0), {"other": fields["flag"]}))
    assert not (tmp_path / "bad.ply").exists()
