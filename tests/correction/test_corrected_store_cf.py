"""``corrected.zarr`` as CF tools and xarray read it: Conventions, flag codes, a flag map plotted on discrete
levels against the scan's angles, and those angles as dimension coordinates where the scan grid is regular."""

from __future__ import annotations

import warnings
from dataclasses import replace

import matplotlib
import numpy as np
import pytest
import xarray as xr
from matplotlib.colors import BoundaryNorm
from matplotlib.figure import Figure

from mpi_lidar.correction import Correction, CorrectionOptions
from mpi_lidar.correction.corrected_store import (
    CF_CONVENTIONS,
    SEPARABLE_TOLERANCE_RAD,
    regular_grid,
    write_corrected_store,
)
from mpi_lidar.correction.options import Estimate, Flag
from mpi_lidar.scans.scan import grid_rays
from mpi_lidar.workflows.verify import verify_store
from tests.scan_factory import two_path_scan
from tests.xarray_checks import open_strictly

pytestmark = pytest.mark.unit


def test_corrected_store__cf_attributes_and_a_discrete_flag_plot(tmp_path):
    matplotlib.use("Agg")
    scan = two_path_scan("cf", height=6, width=8)
    flags = np.full(scan.shape, Flag.NO_MULTIPATH, np.uint8)
    flags[:, :3] = Flag.CORRECTED
    correction = Correction(depth=scan.depth[-1].copy(), flags=flags,
                            estimate=np.full(scan.shape, Estimate.FUSED, np.uint8))
    write_corrected_store(tmp_path / "corrected.zarr", scan, correction, {}, CorrectionOptions())
    ds = xr.open_zarr(tmp_path / "corrected.zarr")
    assert ds.attrs["Conventions"] == CF_CONVENTIONS
    for name, codes in (("flags", Flag), ("estimate", Estimate)):
        attrs = ds[name].attrs
        assert list(attrs["flag_values"]) == [int(c) for c in codes]
        assert attrs["flag_meanings"].split() == [c.name.lower() for c in codes]
        assert list(attrs["valid_range"]) == [0, len(codes) - 1]
    # what docs/reference/flags.md shows: the flags against the angles, one colour per code
    ax = Figure().subplots()
    levels = np.arange(len(ds.flags.flag_values) + 1) - 0.5
    mesh = ds.flags.plot(ax=ax, x="azimuth_rad", y="elevation_rad", levels=levels)
    assert isinstance(mesh.norm, BoundaryNorm) and len(mesh.norm.boundaries) == len(Flag) + 1
    assert ax.get_xlabel().startswith("azimuth") and ax.get_ylabel().startswith("elevation")


def _stored(tmp_path, scan) -> xr.Dataset:
    flags = np.full(scan.shape, Flag.NO_MULTIPATH, np.uint8)
    flags[:, :3] = Flag.CORRECTED
    correction = Correction(depth=scan.depth[-1].copy(), flags=flags)
    write_corrected_store(tmp_path / "corrected.zarr", scan, correction, {}, CorrectionOptions())
    assert verify_store(tmp_path / "corrected.zarr").fingerprinted  # the renamed dimensions pass verify
    return open_strictly(tmp_path / "corrected.zarr")


def _without_grid(scan, rays):
    return replace(scan, azimuth_rad=None, elevation_rad=None, ray_directions=rays)


def test_write_corrected_store__regular_grid_angles_are_dimension_coordinates(tmp_path):
    matplotlib.use("Agg")
    scan = two_path_scan("grid", height=6, width=8)
    ds = _stored(tmp_path, scan)
    assert all(ds[name].dims == ("elevation_rad", "azimuth_rad") for name in ("corrected_depth", "flags"))
    assert set(ds.indexes) == {"elevation_rad", "azimuth_rad"} and "x" not in ds.variables
    np.testing.assert_array_equal(ds.azimuth_rad.values, scan.azimuth_rad)
    np.testing.assert_array_equal(ds.elevation_rad.values, scan.elevation_rad)
    assert ds.azimuth_rad.attrs["units"] == "rad" and ds.elevation_rad.attrs["units"] == "rad"
    # selecting by angle picks the pixel column of that azimuth
    column = ds.corrected_depth.sel(azimuth_rad=scan.azimuth_rad[5]).values
    np.testing.assert_array_equal(column, scan.depth[-1][:, 5])
    # the default plot, no arguments: against the angles, not pixel indices
    ax = Figure().subplots()
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        ds.flags.plot(ax=ax)
    # xarray wraps long labels: compare them with the line breaks as spaces
    assert " ".join(ax.get_xlabel().split()) == "azimuth of the pixel column [rad]"
    assert " ".join(ax.get_ylabel().split()) == "elevation of the pixel row [rad]"
    assert ax.get_xlim()[0] < scan.azimuth_rad[0] and ax.get_xlim()[1] > scan.azimuth_rad[-1]


def test_write_corrected_store__rays_of_a_grid_give_its_angles(tmp_path):
    grid = two_path_scan("rays", height=6, width=8)
    # float32, and 0.05 % longer than unit vectors (the scan's validation allows 0.1 %)
    scan = _without_grid(grid, (1.0005 * grid_rays(grid.azimuth_rad, grid.elevation_rad)).astype(np.float32))
    assert regular_grid(scan) is not None
    ds = _stored(tmp_path, scan)
    assert ds.flags.dims == ("elevation_rad", "azimuth_rad")
    # float32 rays hold each angle to about 1e-7 rad
    np.testing.assert_allclose(ds.azimuth_rad.values, grid.azimuth_rad, rtol=0, atol=SEPARABLE_TOLERANCE_RAD)
    np.testing.assert_allclose(ds.elevation_rad.values, grid.elevation_rad, rtol=0, atol=SEPARABLE_TOLERANCE_RAD)
    assert "ray_directions" in ds.azimuth_rad.attrs["comment"]


def test_write_corrected_store__rolled_rays_keep_pixel_indices(tmp_path):
    """A scanner rolled 10 degrees about its forward axis: each row's rays sweep in elevation too, so no angle per
    column or row labels the maps."""
    grid = two_path_scan("rolled", height=6, width=8)
    rays = grid_rays(grid.azimuth_rad, grid.elevation_rad)
    roll = np.radians(10.0)
    rolled = 1.0005 * rays  # as long as the scan's validation allows
    rolled[..., 0] = 1.0005 * (np.cos(roll) * rays[..., 0] - np.sin(roll) * rays[..., 1])
    rolled[..., 1] = 1.0005 * (np.sin(roll) * rays[..., 0] + np.cos(roll) * rays[..., 1])
    scan = _without_grid(grid, rolled.copy())
    assert regular_grid(scan) is None
    ds = _stored(tmp_path, scan)
    np.testing.assert_array_equal(scan.ray_directions, rolled)  # the scan's own rays are not normalised in place
    assert ds.flags.dims == ("y", "x") and set(ds.indexes) == {"y", "x"}
    assert "azimuth_rad" not in ds.variables


def test_write_corrected_store__azimuths_across_the_back_stay_a_coordinate_of_x(tmp_path):
    """A scan through +-pi: its azimuths are not monotonic, so they cannot index the columns; they still label
    them."""
    grid = two_path_scan("behind", height=6, width=8)
    azimuth = np.angle(np.exp(1j * np.linspace(np.pi - 0.2, np.pi + 0.2, 8)))  # wraps from +pi to -pi
    scan = replace(grid, azimuth_rad=azimuth)
    assert regular_grid(scan) is None
    ds = _stored(tmp_path, scan)
    assert ds.flags.dims == ("y", "x") and "azimuth_rad" in ds.coords and "azimuth_rad" not in ds.indexes
    np.testing.assert_array_equal(ds.azimuth_rad.values, azimuth)
