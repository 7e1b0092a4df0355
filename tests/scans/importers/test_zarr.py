"""The Zarr importer (mpi_lidar.scans.importers.zarr_group), provenance kept from a source's attributes, and
the hint that maps rather than leaves out the measurements."""

from __future__ import annotations

import numpy as np
import pytest
import xarray as xr
import zarr

from mpi_lidar.scans.importers import find_scan_files, load_netcdf, load_scan_file, load_zarr, plan_import
from mpi_lidar.scans.scan import ScanError
from mpi_lidar.scans.store import read_scan, write_scan
from tests.scan_factory import two_path_scan
from tests.scans.importers.files import FREQS, MAPPING, tool_dataset

pytestmark = pytest.mark.unit


def _vendor(scan, operator: str | bytes = "lab 2") -> xr.Dataset:
    ds = tool_dataset(scan)
    ds.attrs = {"instrument": "ToF-3000", "serial": np.int64(4711), "operator": operator}
    return ds


def test_load_zarr__another_tools_group_with_var_mapping(tmp_path):
    scan = two_path_scan("tool", height=6, width=5)
    _vendor(scan).to_zarr(tmp_path / "tool.zarr", mode="w", consolidated=False)
    imported = load_scan_file(tmp_path / "tool.zarr", variables=MAPPING)
    assert imported.name == "tool" and imported.frequencies_hz == FREQS
    np.testing.assert_allclose(imported.depth, scan.depth, rtol=1e-6)
    np.testing.assert_array_equal(imported.amplitude, scan.amplitude)
    np.testing.assert_allclose(imported.azimuth_rad, scan.azimuth_rad, rtol=1e-12)
    source = imported.scene["source"]
    assert source["format"] == "zarr" and source["attributes"] == {"instrument": "ToF-3000", "serial": 4711,
                                                                    "operator": "lab 2"}
    assert source["scalars"]["timestamp"] == {"value": 1.7e9, "units": "seconds since 1970-01-01"}


def test_load_zarr__a_group_written_with_zarr_alone(tmp_path):
    """Arrays without dimension names (zarr v2 and v3) read with one dimension per axis."""
    scan = two_path_scan("plain", height=6, width=5)
    for zarr_format in (2, 3):
        group = zarr.open_group(tmp_path / f"plain{zarr_format}.zarr", mode="w", zarr_format=zarr_format)
        group.create_array("range_m", data=scan.depth)
        group.create_array("amplitude", data=scan.amplitude)
        group.attrs["frequencies_hz"] = list(FREQS)
        group.attrs["serial"] = "A-17"
        imported = load_zarr(tmp_path / f"plain{zarr_format}.zarr", variables={"depth": "range_m"})
        np.testing.assert_array_equal(imported.depth, scan.depth)
        assert imported.scene["source"]["attributes"] == {"serial": "A-17"}


def test_netcdf_provenance__global_attributes_and_a_scalar_timestamp_survive_the_store(tmp_path):
    scan = two_path_scan("vendor", height=6, width=5)
    _vendor(scan, operator=b"lab 2").to_netcdf(tmp_path / "vendor.nc", engine="h5netcdf")
    imported = load_netcdf(tmp_path / "vendor.nc", variables=MAPPING)
    back = read_scan(write_scan(imported, tmp_path / "vendor.scan.zarr"))
    source = back.scene["source"]
    assert source["file"] == "vendor.nc" and source["attributes"]["instrument"] == "ToF-3000"
    assert source["attributes"]["serial"] == 4711 and source["attributes"]["operator"] == "lab 2"
    assert source["scalars"]["timestamp"]["value"] == 1.7e9


def test_find_and_plan__zarr_groups_are_sources_named_without_their_suffix(tmp_path):
    scan = two_path_scan("tool", height=6, width=5)
    _vendor(scan).to_zarr(tmp_path / "day" / "a.zarr", mode="w", consolidated=False)
    write_scan(scan, tmp_path / "day" / "b.scan.zarr")
    (tmp_path / "day" / "empty.zarr").mkdir()
    with pytest.raises(ScanError, match=r"empty\.zarr is not a Zarr group"):
        find_scan_files([tmp_path / "day"])
    files = find_scan_files([tmp_path / "day" / "a.zarr", tmp_path / "day" / "b.scan.zarr"])
    assert [t.name for _, t in plan_import(files, tmp_path / "out")] == ["a.scan.zarr", "b.scan.zarr"]


def test_select_variables__unmapped_depth_is_asked_for_never_left_out(tmp_path):
    ds = _vendor(two_path_scan("tool", height=6, width=5))
    ds.to_zarr(tmp_path / "tool.zarr", mode="w", consolidated=False)
    with pytest.raises(ScanError) as error:
        load_zarr(tmp_path / "tool.zarr", variables={"frequencies_hz": "band_mhz"})
    message = str(error.value)
    assert "--var depth=VARIABLE --var amplitude=VARIABLE" in message
    assert "ignore" not in message and "\n" not in message
