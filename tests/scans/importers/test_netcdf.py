"""The NetCDF/HDF5 importer (mpi_lidar.scans.importers.netcdf)."""

from __future__ import annotations

from dataclasses import replace

import h5py
import numpy as np
import pytest
import xarray as xr

from mpi_lidar.scans.importers import load_netcdf, load_scan_file
from mpi_lidar.scans.scan import ScanError
from mpi_lidar.scans.store import write_scan
from tests.scan_factory import two_path_scan
from tests.scans.importers.files import FREQS, MAPPING, save_npz, tool_dataset

pytestmark = pytest.mark.unit


@pytest.mark.parametrize("engine", ["h5netcdf", "scipy"])  # NetCDF-4 (HDF5) and NetCDF-3 classic
def test_load_netcdf__mapped_variables_in_their_units(tmp_path, engine):
    scan = two_path_scan("tool", height=6, width=5)
    path = tmp_path / "tool.nc"
    tool_dataset(scan).to_netcdf(path, engine=engine)
    imported = load_netcdf(path, variables=MAPPING)
    assert imported.name == "tool" and imported.frequencies_hz == FREQS
    np.testing.assert_allclose(imported.depth, scan.depth, rtol=1e-6)
    np.testing.assert_array_equal(imported.amplitude, scan.amplitude)
    np.testing.assert_allclose(imported.azimuth_rad, scan.azimuth_rad, rtol=1e-12)
    np.testing.assert_allclose(imported.elevation_rad, scan.elevation_rad, rtol=1e-12)


def test_load_netcdf__plain_hdf5_with_store_names(tmp_path):
    scan = two_path_scan("plain", height=6, width=5)
    with h5py.File(tmp_path / "plain.h5", "w") as f:
        f["depth"], f["amplitude"] = scan.depth, scan.amplitude
        f["reference_depth"] = scan.reference_depth
        f["reference_mask"] = scan.reference_mask.astype(np.uint8)
        f["frequencies_hz"] = np.asarray(FREQS)
        f["notes"] = np.zeros(3)  # not a scan array: left out explicitly (refused otherwise)
    imported = load_scan_file(tmp_path / "plain.h5", variables={"ignore": "notes"})
    np.testing.assert_array_equal(imported.depth, scan.depth)
    np.testing.assert_array_equal(imported.reference_mask, scan.reference_mask)
    assert imported.reference_mask.dtype == np.bool_


def test_load_netcdf__a_scan_exported_from_xarray_comes_back(tmp_path):
    """A scan store opened in xarray and saved as NetCDF imports again (frequency_hz coordinate, and the speed of
    light its depths were converted with, an attribute of both)."""
    scan = replace(two_path_scan("round", height=6, width=5), reference_depth=None, reference_mask=None)
    ds = xr.open_zarr(write_scan(scan, tmp_path / "round.scan.zarr"))
    ds.attrs = {"speed_of_light_m_per_s": ds.attrs["speed_of_light_m_per_s"]}
    ds.to_netcdf(tmp_path / "round.nc", engine="h5netcdf")
    back = load_scan_file(tmp_path / "round.nc")
    assert back.content_sha256() == scan.content_sha256()


@pytest.mark.parametrize(("write", "variables", "message"), [
    (lambda p: p.write_bytes(b"\x89HDF\r\n\x1a\n" + b"\0" * 40), None, "not a readable NetCDF/HDF5"),
    (lambda p: p.write_bytes(b"plain text"), None, "neither NetCDF nor HDF5"),
    (lambda p: xr.Dataset({"depth": (("f", "y", "x"), np.ones((4, 2, 2)), {"units": "ft"}),
                           "amplitude": (("f", "y", "x"), np.ones((4, 2, 2)))}).to_netcdf(p, engine="h5netcdf"),
     None, "depth has units 'ft'"),
    (lambda p: xr.Dataset({"depth": (("f", "y", "x"), np.ones((4, 2, 2))),
                           "amplitude": (("f", "y", "x"), np.ones((4, 2, 2)))}).to_netcdf(p, engine="h5netcdf"),
     None, "holds no frequencies_hz"),
    (lambda p: xr.Dataset({"depth": (("f", "y", "x"), np.ones((4, 2, 2)))}).to_netcdf(p, engine="h5netcdf"),
     {"amplitude": "intensity"}, "no variable for --var amplitude=intensity"),
    (lambda p: xr.Dataset({"depth": (("f", "y", "x"), np.full((4, 2, 2), "a"))}).to_netcdf(p, engine="h5netcdf"),
     None, "only numbers and booleans"),
    (lambda p: None, {"colour": "c"}, "not scan arrays"),
    (lambda p: None, {"depth": "d", "reference_depth": "d"}, "map each variable once"),
])
def test_load_netcdf__bad_files_are_one_clear_error(tmp_path, write, variables, message):
    path = tmp_path / "bad.nc"
    write(path)
    if not path.exists():
        save_npz(path)  # any file: the mapping is refused before it is read
    with pytest.raises(ScanError, match=message) as error:
        load_scan_file(path, None, variables)
    assert "\n" not in str(error.value)
