"""The corrected store (``corrected.zarr``) opens in xarray without a warning: coordinates, units, CF flags."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
import zarr

from mpi_lidar.correction import Correction, CorrectionOptions, Flag
from mpi_lidar.correction.corrected_store import write_corrected_store
from mpi_lidar.workflows.verify import verify_store
from tests.scan_factory import two_path_scan
from tests.xarray_checks import open_strictly, plot_strictly

pytestmark = pytest.mark.unit


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
    write_corrected_store(path, scan, correction, {"scan_sha256": scan.content_sha256()}, CorrectionOptions())
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
    write_corrected_store(path, scan, _correction(scan, bias=False), {}, CorrectionOptions())
    ds = open_strictly(path)
    assert set(ds.data_vars) == {"corrected_depth", "flags"} and set(ds.indexes) == {"y", "x"}
    plot_strictly(ds.corrected_depth)
    assert verify_store(path).chunks == 4


def test_corrected_store__second_returns_written_with_their_uncertainty(tmp_path):
    """A pixel resolved into two returns: its weaker return's range, share and 1-sigma are read back as written,
    NaN at every other pixel."""
    from mpi_lidar.correction.mixed import SecondReturns

    scan = two_path_scan("corrected")
    flags = np.full(scan.shape, int(Flag.NO_MULTIPATH), np.uint8)
    flags[1, 2] = Flag.TWO_RETURNS
    maps = [np.full(scan.shape, np.nan, np.float32) for _ in range(4)]
    for values, value in zip(maps, (7.5, 0.3, 0.02, 0.01), strict=True):
        values[1, 2] = value
    correction = replace(_correction(scan), flags=flags, second_returns=SecondReturns(*maps))
    path = tmp_path / "corrected.zarr"
    write_corrected_store(path, scan, correction, {}, CorrectionOptions())
    ds = open_strictly(path)
    for name, written in zip(("second_return_depth", "second_return_share", "second_return_uncertainty"), maps,
                             strict=False):
        np.testing.assert_array_equal(ds[name].values, written)
    assert ds.second_return_uncertainty.attrs["units"] == "m"
