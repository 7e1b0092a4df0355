"""``corrected.zarr`` as CF tools and xarray read it: Conventions, flag codes, and a flag map plotted on discrete
levels against the scan's angles."""

from __future__ import annotations

import matplotlib
import numpy as np
import pytest
import xarray as xr
from matplotlib.colors import BoundaryNorm
from matplotlib.figure import Figure

from mpi_lidar.correction import Correction, CorrectionOptions
from mpi_lidar.correction.corrected_store import CF_CONVENTIONS, write_corrected_store
from mpi_lidar.correction.options import Estimate, Flag
from tests.scan_factory import two_path_scan

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
