"""What the point clouds of a corrected scan hold, read back as viewers read them: laspy for LAS/LAZ (intensity,
withheld points, the JSON record of flag codes and frame, the generator), plyfile for PLY (field names)."""

from __future__ import annotations

from dataclasses import replace

import laspy
import numpy as np
import pytest
from plyfile import PlyData

from mpi_lidar.correction import Correction
from mpi_lidar.correction.options import INVALID_FLAGS, Flag
from mpi_lidar.reporting.legend import FLAG_LEGEND
from mpi_lidar.reporting.point_cloud_files import (
    FLAG_LETTERS,
    POINT_CLOUD_FILES,
    SCANNER_FRAME,
    flag_description,
    frame_record,
    point_cloud_colors,
    write_point_clouds,
)
from mpi_lidar.scans.pointcloud import (
    INTENSITY_MAX,
    INTENSITY_PER_COUNT_V2,
    LAS_CLASS_LOW_NOISE,
    PLY_SCALAR_PREFIX,
    PointCloudFormat,
    PointCloudFrame,
    generator,
    las_metadata,
)
from tests.scan_factory import two_path_scan

pytestmark = pytest.mark.unit

H, W = 14, 12


@pytest.fixture
def corrected():
    """A corrected scan: flags of every code, invalid pixels NaN in the corrected depth, one of them (not finite)
    NaN in the raw depth too, one (no return) with a negative measured range, as noise gives where there is no light."""
    scan = two_path_scan("contents", height=H, width=W)
    measured = scan.depth[-1].copy()
    flags = np.full((H, W), Flag.NO_MULTIPATH, np.uint8)
    flags[:, : W // 2] = Flag.CORRECTED
    for index, flag in enumerate(Flag):
        flags[index, W - 1] = flag
    flags[4, 3], flags[5, 3] = Flag.NOT_FINITE, Flag.SATURATED
    measured[flags == Flag.NOT_FINITE] = np.nan
    measured[flags == Flag.NO_RETURN] = -0.4
    invalid = np.isin(flags, [int(f) for f in INVALID_FLAGS])
    depth = np.where(flags == Flag.CORRECTED, measured - 0.003, measured).astype(np.float32)
    depth[invalid] = np.nan
    correction = Correction(depth=depth, flags=flags, measured_depth=measured,
                            uncertainty_m=np.full((H, W), 0.0015, np.float32))
    return scan, measured, correction


def _write(tmp_path, corrected, formats, uncertainty=True, **options):
    scan, _, correction = corrected
    if not uncertainty:
        correction = replace(correction, uncertainty_m=None)
    return write_point_clouds(tmp_path, formats, scan.rays(), scan, correction, **options)


def _placed(measured, correction):
    """Pixels with a point by default: valid ones, and invalid ones with a return and a positive measured range."""
    rangeless = np.isin(correction.flags, [Flag.NOT_FINITE, Flag.NO_RETURN, Flag.BEYOND_AMBIGUITY])
    return np.isfinite(correction.depth) | (~rangeless & (measured > 0))


def test_flag_description__every_code_in_31_characters():
    text = flag_description()
    assert len(text) <= 31
    assert set(FLAG_LETTERS) == set(FLAG_LEGEND) == set(Flag), "a new flag needs its letter and meaning"
    assert len(set(FLAG_LETTERS.values())) == len(Flag)
    assert sorted(int(flag) for flag in Flag) == list(range(len(Flag))), "flag codes run 0, 1, 2, ... without a gap"
    letters = text.split(": ", 1)[1] if text.startswith("flags ") else None
    for flag in Flag:
        if letters is None:
            assert f"{int(flag)}{FLAG_LETTERS[flag]}" in text
        else:
            assert letters[int(flag)] == FLAG_LETTERS[flag]


def test_write_point_clouds__laz_intensity_withheld_record_and_generator(tmp_path, corrected):
    scan, measured, correction = corrected
    assert _write(tmp_path, corrected, (PointCloudFormat.LAZ,)) == ["corrected.laz"]
    las = laspy.read(tmp_path / "corrected.laz")
    # valid pixels and invalid ones with a range of their own are points; the invalid ones withheld, as noise
    placed = _placed(measured, correction)
    assert las.header.point_count == placed.sum()
    assert not np.isin(np.asarray(las.flag), [Flag.NOT_FINITE, Flag.NO_RETURN]).any(), "no range: no point"
    assert np.asarray(las.withheld).sum() == (placed & np.isnan(correction.depth)).sum() > 0
    withheld = np.asarray(las.withheld, bool)
    assert set(np.asarray(las.flag)[withheld]) <= {int(f) for f in INVALID_FLAGS}
    assert set(np.asarray(las.classification)[withheld]) == {LAS_CLASS_LOW_NOISE}
    # a withheld point sits at its raw range; the others at their corrected range
    rows, columns = np.asarray(las.row), np.asarray(las.column)
    ranges = np.linalg.norm(np.stack([las.x, las.y, las.z], axis=1), axis=1)
    np.testing.assert_allclose(ranges[withheld], measured[rows[withheld], columns[withheld]], atol=2e-4)
    np.testing.assert_allclose(ranges[~withheld], correction.depth[rows[~withheld], columns[~withheld]], atol=2e-4)
    assert np.all(np.isnan(np.asarray(las.corrected_range_m)[withheld]))
    # intensity: the amplitude over one fixed scale, the same in every file
    record = las_metadata(tmp_path / "corrected.laz")
    amplitude = scan.amplitude[-1][rows, columns].astype(np.float64)
    scale = record["intensity"]["per_count"]
    assert scale == INTENSITY_PER_COUNT_V2
    np.testing.assert_array_equal(las.intensity, np.clip(np.rint(amplitude / scale), 0, INTENSITY_MAX))
    # the JSON record: every flag code with its name, which are invalid, and the frame
    assert {int(code): entry["name"] for code, entry in record["flags"].items()} == {
        int(flag): flag.name.lower() for flag in Flag}
    assert {int(code) for code, entry in record["flags"].items() if entry["invalid"]} == {int(f) for f in INVALID_FLAGS}
    assert record["frame"] == {"name": "scanner", **SCANNER_FRAME} and record["generator"] == generator()
    assert "raw range" not in str(record["flags"]), "uncorrected pixels hold the baseline, not the raw range"
    # the header's bounds are the written points'
    xyz = np.stack([las.x, las.y, las.z], axis=1)
    np.testing.assert_allclose(las.header.mins, xyz.min(0), atol=1e-4)
    np.testing.assert_allclose(las.header.maxs, xyz.max(0), atol=1e-4)
    assert las.header.version.major == 1 and las.header.version.minor == 4
    assert las.header.generating_software.startswith("mpi-lidar")
    descriptions = {p.name: p.description for p in las.point_format.extra_dimensions}
    assert descriptions["flag"] == flag_description() and descriptions["uncertainty_m"].endswith("[m]")
    np.testing.assert_array_equal(las.uncertainty_m, np.float32(0.0015))


def test_write_point_clouds__points_follow_grid_rays(tmp_path, corrected):
    """x = cos(el) sin(az) r, y = sin(el) r, z = cos(el) cos(az) r, as the frame record says."""
    scan, _, correction = corrected
    _write(tmp_path, corrected, (PointCloudFormat.LAS,))
    las = laspy.read(tmp_path / "corrected.las")
    keep = ~np.asarray(las.withheld, bool)
    az, el = scan.azimuth_rad[np.asarray(las.column)][keep], scan.elevation_rad[np.asarray(las.row)][keep]
    r = correction.depth[np.asarray(las.row)[keep], np.asarray(las.column)[keep]]
    expected = np.stack([np.cos(el) * np.sin(az) * r, np.sin(el) * r, np.cos(el) * np.cos(az) * r], axis=1)
    np.testing.assert_allclose(np.stack([las.x, las.y, las.z], axis=1)[keep], expected, atol=1e-4)


def test_write_point_clouds__no_uncertainty_no_field(tmp_path, corrected):
    _write(tmp_path, corrected, (PointCloudFormat.LAZ,), uncertainty=False)
    assert "uncertainty_m" not in laspy.read(tmp_path / "corrected.laz").point_format.extra_dimension_names


def test_write_point_clouds__ply_scalar_fields_colours_valid_points(tmp_path, corrected):
    _, measured, correction = corrected
    assert _write(tmp_path, corrected, (PointCloudFormat.PLY,)) == list(POINT_CLOUD_FILES[PointCloudFormat.PLY])
    for name in ("raw.ply", "corrected.ply"):
        vertex = PlyData.read(str(tmp_path / name))["vertex"]
        names = [p.name for p in vertex.properties]
        assert names[:6] == ["x", "y", "z", "red", "green", "blue"], "what Open3D reads"
        assert all(n.startswith(PLY_SCALAR_PREFIX) for n in names[6:]), "what CloudCompare reads as scalar fields"
        assert {n.removeprefix(PLY_SCALAR_PREFIX) for n in names[6:]} == {
            "raw_range_m", "corrected_range_m", "correction_mm", "flag", "amplitude_v2", "uncertainty_m", "row",
            "column"}
        assert vertex.count == np.isfinite(correction.depth).sum(), "PLY holds the valid points only"
        ranges = np.linalg.norm(np.stack([vertex["x"], vertex["y"], vertex["z"]], axis=1), axis=1)
        source = measured if name == "raw.ply" else correction.depth
        np.testing.assert_allclose(ranges, source[vertex["scalar_row"], vertex["scalar_column"]], rtol=1e-5)


def test_point_cloud_colors__grey_by_amplitude_amber_where_corrected():
    flags = np.array([[Flag.CORRECTED, Flag.NO_MULTIPATH, Flag.NO_MULTIPATH, Flag.NOT_FINITE]], np.uint8)
    amplitude = np.array([[1.0, 1.0, 0.25, np.nan]], np.float32)
    rgb = point_cloud_colors(flags, amplitude)
    assert rgb.dtype == np.uint8 and rgb.shape == (1, 4, 3)
    assert tuple(rgb[0, 1]) == (255, 255, 255) and tuple(rgb[0, 3]) == (40, 40, 40)
    assert rgb[0, 2, 0] == rgb[0, 2, 1] == rgb[0, 2, 2] == round(40 + 215 * 0.5)
    assert rgb[0, 0, 0] == 255 and rgb[0, 0, 0] > rgb[0, 0, 1] > rgb[0, 0, 2], "amber"


def test_write_point_clouds__no_return_kept_on_its_ray_at_the_stated_range(tmp_path, corrected):
    scan, _, correction = corrected
    _write(tmp_path, corrected, (PointCloudFormat.LAS,), no_return_range_m=0.5)
    las = laspy.read(tmp_path / "corrected.las")
    flags, withheld = np.asarray(las.flag), np.asarray(las.withheld, bool)
    kept = np.isin(flags, [Flag.NOT_FINITE, Flag.NO_RETURN])
    assert kept.sum() == np.isin(correction.flags, [Flag.NOT_FINITE, Flag.NO_RETURN]).sum() and withheld[kept].all()
    xyz = np.stack([las.x, las.y, las.z], axis=1)
    np.testing.assert_allclose(np.linalg.norm(xyz[kept], axis=1), 0.5, atol=2e-4)
    rays = scan.rays()[np.asarray(las.row)[kept], np.asarray(las.column)[kept]]
    assert (np.sum(xyz[kept] * rays, axis=1) > 0).all(), "on its ray, never behind the scanner"
    assert "0.5 m" in str(las_metadata(tmp_path / "corrected.las")["withheld_points"])


def test_write_point_clouds__z_up_frame(tmp_path, corrected):
    for folder in ("scanner", "z"):
        (tmp_path / folder).mkdir()
    _write(tmp_path / "scanner", corrected, (PointCloudFormat.LAS,))
    _write(tmp_path / "z", corrected, (PointCloudFormat.LAS,), frame=PointCloudFrame.Z_UP)
    scanner, z_up = (laspy.read(tmp_path / d / "corrected.las") for d in ("scanner", "z"))
    np.testing.assert_array_equal(z_up.x, scanner.z)  # forward
    np.testing.assert_array_equal(z_up.y, scanner.x)  # the scanner's left
    np.testing.assert_array_equal(z_up.z, scanner.y)  # up
    assert las_metadata(tmp_path / "z" / "corrected.las")["frame"] == frame_record("z-up")
