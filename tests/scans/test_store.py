"""The scan store (mpi_lidar.scans.store): round trips, refusals, the xarray view, the declared variables."""

from __future__ import annotations

import json
import shutil
from dataclasses import replace

import numpy as np
import pytest
import zarr

from mpi_lidar.config import Config
from mpi_lidar.physics.demod import taps_from_quadratures
from mpi_lidar.scans.scan import ScanError
from mpi_lidar.scans.store import SCAN_SCHEMA, read_scan, store_fingerprints, write_scan
from mpi_lidar.storage.variables import SCAN
from mpi_lidar.workflows.verify import verify_store
from tests.scan_factory import two_path_scan
from tests.xarray_checks import open_strictly, plot_strictly

pytestmark = pytest.mark.unit

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
    group.attrs.update({"schema": "mpi-lidar/scan@1", "frequencies_hz": list(FREQS),
                        "chunk_sha256": store_fingerprints(group)})
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
    with pytest.raises(ScanError, match=r"is not a scan store .*import it first"):
        read_scan(tmp_path / "foreign.zarr")
    path = write_scan(two_path_scan("t"), tmp_path / "t.scan.zarr")
    shutil.rmtree(path / "amplitude")
    with pytest.raises(ScanError, match=r"neither depth\+amplitude nor taps|truncated|damaged"):
        read_scan(path)


def test_scan_store__xarray_sees_coordinates_and_units(tmp_path):
    scan = two_path_scan("frame")
    path = write_scan(scan, tmp_path / "frame.scan.zarr")
    assert "consolidated_metadata" in json.loads((path / "zarr.json").read_text())
    ds = open_strictly(path)
    assert set(ds.coords) == {"frequency_hz", "azimuth_rad", "elevation_rad"}
    np.testing.assert_array_equal(ds.frequency_hz, scan.frequencies_hz)
    np.testing.assert_array_equal(ds.azimuth_rad, scan.azimuth_rad)
    np.testing.assert_array_equal(ds.elevation_rad, scan.elevation_rad)
    assert ds.depth.dims == ("frequency", "y", "x") and ds.azimuth_rad.dims == ("x",)
    np.testing.assert_array_equal(ds.depth.values, scan.depth)
    units = {name: ds[name].attrs["units"] for name in ds.variables}
    assert units == {"depth": "m", "amplitude": "V^2", "reference_depth": "m", "reference_mask": "1",
                     "frequency_hz": "Hz", "azimuth_rad": "rad", "elevation_rad": "rad"}
    assert all(ds[name].attrs["long_name"] for name in ds.variables)
    plot_strictly(ds.depth.isel(frequency=-1))
    plot_strictly(ds.depth)  # a histogram of all three dimensions
    plot_strictly(ds.reference_depth)


def test_scan_store__without_geometry_gets_pixel_indices(tmp_path):
    scan = replace(two_path_scan("bare"), azimuth_rad=None, elevation_rad=None, reference_mask=None)
    ds = open_strictly(write_scan(scan, tmp_path / "bare.scan.zarr"))
    assert set(ds.coords) == {"frequency_hz", "y", "x"} and set(ds.indexes) == {"y", "x"}
    np.testing.assert_array_equal(ds.x, np.arange(scan.shape[1]))
    assert ds.y.attrs == {"units": "1", "long_name": "pixel row"}
    plot_strictly(ds.depth.isel(frequency=0))


def test_scan_store__readers_and_identity_are_unchanged(tmp_path):
    scan = replace(two_path_scan("same"), ray_directions=two_path_scan("same").rays().astype(np.float32))
    path = write_scan(scan, tmp_path / "same.scan.zarr")
    back = read_scan(path)
    assert back.content_sha256() == scan.content_sha256()
    assert back.frequencies_hz == scan.frequencies_hz
    np.testing.assert_array_equal(back.ray_directions, scan.ray_directions)
    group = zarr.open_group(str(path), mode="r")
    assert set(group.attrs["chunk_sha256"]) == set(group.array_keys())  # the coordinates are fingerprinted
    assert verify_store(path).fingerprinted
    ds = open_strictly(path)
    assert ds.ray_directions.dims == ("y", "x", "xyz")
    assert set(ds.ray_directions.coords) == {"azimuth_rad", "elevation_rad"}
    assert set(ds.depth.coords) == {"frequency_hz", "azimuth_rad", "elevation_rad"}


def _write_old_scan_store(scan, path) -> None:
    """A store as written before the xarray coordinates: no coordinate arrays, no units, not consolidated."""
    group = zarr.open_group(store=str(path), mode="w-")
    for name in ("depth", "amplitude"):
        group.create_array(name, data=getattr(scan, name), dimension_names=("frequency", "y", "x"))
    group.create_array("azimuth_rad", data=scan.azimuth_rad, dimension_names=("x",))
    group.create_array("elevation_rad", data=scan.elevation_rad, dimension_names=("y",))
    group.attrs.update({"schema": SCAN_SCHEMA, "frequencies_hz": list(scan.frequencies_hz), "name": scan.name,
                        "scene": {}, "chunk_sha256": store_fingerprints(group)})


def test_scan_store__stores_written_before_still_read(tmp_path):
    scan = replace(two_path_scan("old"), reference_depth=None, reference_mask=None)
    _write_old_scan_store(scan, tmp_path / "old.scan.zarr")
    back = read_scan(tmp_path / "old.scan.zarr")
    assert back.content_sha256() == scan.content_sha256()
    assert verify_store(tmp_path / "old.scan.zarr").kind == "scan"
    new = write_scan(scan, tmp_path / "new.scan.zarr")
    assert read_scan(new).content_sha256() == back.content_sha256()


def test_scan_store__altered_frequency_coordinate_is_refused(tmp_path):
    path = write_scan(two_path_scan("f"), tmp_path / "f.scan.zarr")
    group = zarr.open_group(str(path), mode="r+", use_consolidated=False)
    group.attrs["frequencies_hz"] = [1e6, 2e6, 3e6, 4e6]
    with pytest.raises(ScanError, match=r"frequency_hz array .* differs"):
        read_scan(path)


def test_write_scan__every_array_written_is_declared_with_its_dims_and_attributes(tmp_path):
    scan = replace(two_path_scan("all"), ray_directions=two_path_scan("all").rays().astype(np.float32))
    bare = replace(scan, azimuth_rad=None, elevation_rad=None)
    for name, written in (("all", scan), ("bare", bare)):
        group = zarr.open_group(str(write_scan(written, tmp_path / f"{name}.scan.zarr")), mode="r")
        for array_name, array in group.arrays():
            declared = SCAN[array_name]  # KeyError: an array the registry does not declare
            assert tuple(array.metadata.dimension_names) == declared.dims
            assert (array.attrs["units"], array.attrs["long_name"]) == (declared.units, declared.long_name)
            assert declared.accepts(array.dtype), array_name


@pytest.mark.parametrize(("name", "values", "message"), [
    ("reference_mask", lambda s: s.reference_mask.astype(np.float32), "reference_mask must be boolean, got float32"),
    ("depth", lambda s: s.depth.astype(np.int32), "depth must be floating point, got int32"),
    ("azimuth_rad", lambda s: np.arange(s.shape[1]), "azimuth_rad must be floating point, got int64"),
])
def test_read_scan__an_array_of_another_dtype_than_declared_is_refused_in_one_line(tmp_path, name, values, message):
    scan = two_path_scan("typed")
    path = write_scan(scan, tmp_path / "typed.scan.zarr")
    group = zarr.open_group(str(path), mode="r+", use_consolidated=False)
    attributes = dict(group[name].attrs)
    del group[name]
    group.create_array(name, data=values(scan), dimension_names=SCAN[name].dims, attributes=attributes)
    group.attrs["chunk_sha256"] = store_fingerprints(group)  # the fingerprints hold: only the dtype is wrong
    with pytest.raises(ScanError, match=message) as error:
        read_scan(path)
    assert "\n" not in str(error.value) and str(path) in str(error.value)
