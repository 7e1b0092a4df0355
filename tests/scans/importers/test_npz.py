"""The .npz importer (mpi_lidar.scans.importers.npz)."""

from __future__ import annotations

import numpy as np
import pytest

from mpi_lidar.scans.importers import import_arrays, load_npz, load_scan_file
from mpi_lidar.scans.scan import ScanError
from tests.scan_factory import two_path_scan
from tests.scans.importers.files import FREQS

pytestmark = pytest.mark.unit


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


def test_load_npz__mapped_member_names(tmp_path):
    scan = two_path_scan("mapped", height=6, width=5)
    np.savez(tmp_path / "mapped.npz", range_m=scan.depth, intensity=scan.amplitude, frequencies_hz=FREQS)
    imported = load_scan_file(tmp_path / "mapped.npz", variables={"depth": "range_m", "amplitude": "intensity"})
    np.testing.assert_array_equal(imported.depth, scan.depth)
    np.savez(tmp_path / "both.npz", depth=scan.depth, range_m=scan.depth, amplitude=scan.amplitude)
    with pytest.raises(ScanError, match=r"holds \['depth'\] itself"):
        load_scan_file(tmp_path / "both.npz", FREQS, {"depth": "range_m"})
