from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
import zarr

from mpi_lidar.config import Config
from mpi_lidar.physics.demod import taps_from_quadratures
from mpi_lidar.scans import geometry
from mpi_lidar.scans.scan import ScanError, grid_rays, import_arrays, load_npz, read_scan, write_scan
from tests.scan_factory import two_path_scan

FREQS = Config().frequencies_hz


def test_write_scan__round_trip_keeps_every_array(tmp_path):
    scan = two_path_scan("round")
    back = read_scan(write_scan(scan, tmp_path / "round.scan.zarr"))
    assert back.name == "round" and back.frequencies_hz == FREQS
    for name in ("depth", "amplitude", "azimuth_rad", "elevation_rad", "reference_depth", "reference_mask"):
        np.testing.assert_array_equal(getattr(back, name), getattr(scan, name))
    assert back.content_sha256() == scan.content_sha256()


def test_write_scan__existing_store_is_not_overwritten(tmp_path):
    path = write_scan(two_path_scan("a"), tmp_path / "a.scan.zarr")
    with pytest.raises(ScanError, match="already exists"):
        write_scan(two_path_scan("a", seed=1), path)
    assert read_scan(path).content_sha256() == two_path_scan("a").content_sha256()


def test_read_scan__taps_only_store_is_demodulated(tmp_path):
    rng = np.random.default_rng(0)
    phase = rng.uniform(0.1, 6.0, (4, 5, 6))
    gamma = rng.uniform(0.01, 0.05, (4, 5, 6))
    taps = np.moveaxis(taps_from_quadratures(gamma * np.cos(phase), gamma * np.sin(phase)), -1, 1)
    group = zarr.open_group(str(tmp_path / "t.scan.zarr"), mode="w")
    group.create_array("taps", data=taps.astype(np.float64))
    group.attrs.update({"schema": "mpi-lidar/scan@1", "frequencies_hz": list(FREQS)})
    scan = read_scan(tmp_path / "t.scan.zarr")
    expected = 3e8 * phase / (4 * np.pi * np.asarray(FREQS)[:, None, None])
    np.testing.assert_allclose(scan.depth, expected, rtol=1e-6)
    np.testing.assert_allclose(scan.amplitude, gamma, rtol=1e-6)


@pytest.mark.parametrize(("change", "message"), [
    ({"amplitude": np.zeros((4, 24, 31), np.float32)}, "differs from depth shape"),
    ({"amplitude": -np.ones((4, 24, 32), np.float32)}, "negative values"),
    ({"depth": np.full((4, 24, 32), np.nan, np.float32)}, "no pixel has a finite depth"),
    ({"frequencies_hz": (12.5e6, 25e6)}, "depth must have shape"),
    ({"reference_depth": np.zeros((3, 3), np.float32)}, "reference_depth must have shape"),
    ({"depth": np.zeros((4, 24, 32), np.int32)}, "floating point"),
])
def test_write_scan__bad_arrays_are_refused_in_one_line(tmp_path, change, message):
    with pytest.raises(ScanError, match=message) as error:
        write_scan(replace(two_path_scan("bad"), **change), tmp_path / "bad.scan.zarr")
    assert "\n" not in str(error.value)
    assert not (tmp_path / "bad.scan.zarr").exists()
    assert not any(tmp_path.iterdir()), "no partial output"


def test_read_scan__foreign_and_truncated_stores_are_refused(tmp_path):
    zarr.open_group(str(tmp_path / "foreign.zarr"), mode="w").attrs["schema"] = "other"
    with pytest.raises(ScanError, match="not an mpi-lidar scan"):
        read_scan(tmp_path / "foreign.zarr")
    path = write_scan(two_path_scan("t"), tmp_path / "t.scan.zarr")
    import shutil

    shutil.rmtree(path / "amplitude")
    with pytest.raises(ScanError, match=r"neither depth\+amplitude nor taps|truncated|damaged"):
        read_scan(path)


def test_load_npz__imports_arrays_from_other_tools(tmp_path):
    scan = two_path_scan("npz")
    np.savez(tmp_path / "from_tool.npz", depth=scan.depth, amplitude=scan.amplitude, azimuth_rad=scan.azimuth_rad,
             elevation_rad=scan.elevation_rad, frequencies_hz=np.asarray(FREQS))
    imported = load_npz(tmp_path / "from_tool.npz")
    assert imported.name == "from_tool" and imported.has_geometry
    np.testing.assert_array_equal(imported.depth, scan.depth)
    with pytest.raises(ScanError, match="unknown arrays"):
        import_arrays("x", FREQS, {"depth": scan.depth, "amplitude": scan.amplitude, "colour": scan.depth})


def test_load_npz__object_arrays_are_refused_without_unpickling(tmp_path):
    np.save(tmp_path / "evil.npy", np.array([object()], dtype=object), allow_pickle=True)
    np.savez(tmp_path / "evil.npz", depth=np.array([{"a": 1}], dtype=object))
    with pytest.raises(ScanError, match=r"(not a readable \.npz|has dtype object)"):
        load_npz(tmp_path / "evil.npz", FREQS)


def test_grid_rays__unit_vectors_along_the_documented_axes():
    rays = grid_rays(np.array([0.0, np.pi / 2]), np.array([0.0, np.pi / 2]))
    np.testing.assert_allclose(np.linalg.norm(rays, axis=-1), 1.0)
    np.testing.assert_allclose(rays[0, 0], [0, 0, 1], atol=1e-12)  # forward
    np.testing.assert_allclose(rays[0, 1], [1, 0, 0], atol=1e-12)  # right
    np.testing.assert_allclose(rays[1, 0], [0, 1, 0], atol=1e-12)  # up


def test_surface_normals__plane_gives_its_normal_towards_the_scanner():
    az, el = np.linspace(-0.3, 0.3, 20), np.linspace(-0.2, 0.2, 15)
    rays = grid_rays(az, el)
    normal = np.array([0.3, 0.0, -1.0]) / np.linalg.norm([0.3, 0.0, -1.0])
    depth = 2.0 / -(rays @ normal)  # plane n . p = -2
    normals = geometry.surface_normals(geometry.point_cloud(depth, rays))
    np.testing.assert_allclose(normals[2:-2, 2:-2], np.broadcast_to(normal, normals[2:-2, 2:-2].shape), atol=1e-9)

