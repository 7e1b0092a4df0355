"""Scan stores and corrected stores open in xarray without a warning: coordinates, units, flags, consolidated."""

from __future__ import annotations

import json
import warnings
from dataclasses import replace

import matplotlib
import numpy as np
import pytest
import xarray as xr
import zarr

from mpi_lidar.correction import Correction, CorrectionOptions, Flag
from mpi_lidar.reporting.scan_report import _write_corrected_store
from mpi_lidar.scans.scan import (
    SCAN_SCHEMA,
    ScanError,
    read_scan,
    store_fingerprints,
    write_scan,
)
from mpi_lidar.workflows.verify import verify_store
from tests.scan_factory import two_path_scan

matplotlib.use("Agg")


def open_strictly(path) -> xr.Dataset:
    """The store in xarray, every warning an error (unconsolidated metadata, decoding, ...), values loaded."""
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        return xr.open_zarr(path).load()


def plot_strictly(array: xr.DataArray) -> None:
    import matplotlib.pyplot as plt

    with warnings.catch_warnings():
        warnings.simplefilter("error")
        array.plot()
    plt.close("all")


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


def _correction(scan, bias: bool = True) -> Correction:
    flags = np.full(scan.shape, int(Flag.NO_MULTIPATH), np.uint8)
    flags[:, : scan.shape[1] // 2] = Flag.CORRECTED
    flags[0, 0] = Flag.NOT_FINITE
    depth = scan.depth[-1] - 0.003 * (flags == Flag.CORRECTED)
    depth[0, 0] = np.nan
    return Correction(depth=depth.astype(np.float32), flags=flags, inference_s=0.0, total_s=0.0,
                      multipath_bias_m=np.full(scan.shape, 0.002, np.float32) if bias else None)


def test_corrected_store__xarray_plots_corrected_depth_with_cf_flags(tmp_path):
    scan = two_path_scan("corrected")
    correction = _correction(scan)
    path = tmp_path / "corrected.zarr"
    _write_corrected_store(path, scan, correction, {"scan_sha256": scan.content_sha256()}, CorrectionOptions())
    ds = open_strictly(path)
    assert set(ds.data_vars) == {"corrected_depth", "flags", "multipath_bias_m"}
    assert set(ds.coords) == {"azimuth_rad", "elevation_rad"}
    np.testing.assert_array_equal(ds.corrected_depth.values, correction.depth)
    np.testing.assert_array_equal(ds.flags.values, correction.flags)
    assert ds.corrected_depth.attrs["units"] == "m" and ds.multipath_bias_m.attrs["units"] == "m"
    flags = ds.flags.attrs
    assert flags["flag_values"] == [int(f) for f in Flag]
    assert flags["flag_meanings"].split() == [f.name.lower() for f in Flag]
    assert all("units" in ds[name].attrs and "long_name" in ds[name].attrs for name in ds.variables)
    plot_strictly(ds.corrected_depth)
    plot_strictly(ds.flags)
    assert verify_store(path).fingerprinted  # every array, coordinates included, checked chunk by chunk
    assert zarr.open_group(str(path), mode="r").attrs["scan_sha256"] == scan.content_sha256()


def test_corrected_store__scan_without_geometry_gets_pixel_indices(tmp_path):
    scan = replace(two_path_scan("bare"), azimuth_rad=None, elevation_rad=None)
    path = tmp_path / "corrected.zarr"
    _write_corrected_store(path, scan, _correction(scan, bias=False), {}, CorrectionOptions())
    ds = open_strictly(path)
    assert set(ds.data_vars) == {"corrected_depth", "flags"} and set(ds.indexes) == {"y", "x"}
    plot_strictly(ds.corrected_depth)
    assert verify_store(path).chunks == 4
