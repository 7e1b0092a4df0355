"""Scans in: .npz, NetCDF-4, NetCDF-3 and plain HDF5 files, mapped variable names, many files in one call."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import h5py
import numpy as np
import pytest
import xarray as xr

from mpi_lidar.scans.scan import ScanError, find_scan_files, load_netcdf, load_scan_file, plan_import, read_scan
from tests.cli_runner import assert_one_error_line, call_main
from tests.scan_factory import two_path_scan

FREQS = two_path_scan("f").frequencies_hz


def save_npz(path: Path, name: str = "frame", seed: int = 0) -> Path:
    scan = two_path_scan(name, height=6, width=5, seed=seed)
    np.savez(path, depth=scan.depth, amplitude=scan.amplitude, azimuth_rad=scan.azimuth_rad,
             elevation_rad=scan.elevation_rad, frequencies_hz=np.asarray(FREQS))
    return path


def tool_dataset(scan) -> xr.Dataset:
    """A scan as another tool might write it: its own names, range in mm, angles in degrees, MHz."""
    dims = ("band", "row", "col")
    return xr.Dataset(
        {"range_mm": (dims, 1e3 * scan.depth.astype(np.float64), {"units": "mm"}),
         "intensity": (dims, scan.amplitude),
         "az": (("col",), np.degrees(scan.azimuth_rad), {"units": "degrees"}),
         "el": (("row",), np.degrees(scan.elevation_rad), {"units": "degree"}),
         "timestamp": ((), 1.7e9, {"units": "seconds since 1970-01-01"})},
        coords={"band_mhz": (("band",), np.asarray(FREQS) / 1e6, {"units": "MHz"})},
    )


MAPPING = {"depth": "range_mm", "amplitude": "intensity", "azimuth_rad": "az", "elevation_rad": "el",
           "frequencies_hz": "band_mhz"}


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
        f["notes"] = np.zeros(3)  # not a scan array: ignored
    imported = load_scan_file(tmp_path / "plain.h5")
    np.testing.assert_array_equal(imported.depth, scan.depth)
    np.testing.assert_array_equal(imported.reference_mask, scan.reference_mask)
    assert imported.reference_mask.dtype == np.bool_


def test_load_netcdf__a_scan_exported_from_xarray_comes_back(tmp_path):
    """A scan store opened in xarray and saved as NetCDF imports again (frequency_hz coordinate)."""
    from mpi_lidar.scans.scan import write_scan

    scan = replace(two_path_scan("round", height=6, width=5), reference_depth=None, reference_mask=None)
    ds = xr.open_zarr(write_scan(scan, tmp_path / "round.scan.zarr"))
    ds.attrs = {}
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


def test_load_npz__mapped_member_names(tmp_path):
    scan = two_path_scan("mapped", height=6, width=5)
    np.savez(tmp_path / "mapped.npz", range_m=scan.depth, intensity=scan.amplitude, frequencies_hz=FREQS)
    imported = load_scan_file(tmp_path / "mapped.npz", variables={"depth": "range_m", "amplitude": "intensity"})
    np.testing.assert_array_equal(imported.depth, scan.depth)
    np.savez(tmp_path / "both.npz", depth=scan.depth, range_m=scan.depth, amplitude=scan.amplitude)
    with pytest.raises(ScanError, match=r"holds \['depth'\] itself"):
        load_scan_file(tmp_path / "both.npz", FREQS, {"depth": "range_m"})


def test_find_and_plan__directories_globs_and_clashes(tmp_path):
    day = tmp_path / "day"
    day.mkdir()
    for name in ("a", "b"):
        save_npz(day / f"{name}.npz", name)
    (day / "notes.txt").write_text("not a scan")
    (day / ".hidden.npz").write_bytes(b"")
    files = find_scan_files([day, str(day / "*.npz"), day / "a.npz"])
    assert [p.name for p in files] == ["a.npz", "b.npz"]
    plan = plan_import(files, tmp_path / "out")
    assert [t.name for _, t in plan] == ["a.scan.zarr", "b.scan.zarr"]
    with pytest.raises(ScanError, match="matches no"):
        find_scan_files([str(day / "*.nc")])
    with pytest.raises(ScanError, match="does not exist"):
        find_scan_files([tmp_path / "missing.npz"])
    save_npz(tmp_path / "a.npz", "a")
    with pytest.raises(ScanError, match="would both be written"):
        plan_import([day / "a.npz", tmp_path / "a.npz"], tmp_path / "out")
    with pytest.raises(ScanError, match="is one scan store"):
        plan_import(files, tmp_path / "x.scan.zarr")


def test_import_scan_cli__a_day_of_frames_in_one_call(tmp_path, monkeypatch, capsys):
    day = tmp_path / "day"
    day.mkdir()
    save_npz(day / "f1.npz", "f1", seed=1)
    save_npz(day / "f2.npz", "f2", seed=2)
    tool_dataset(two_path_scan("f3", height=6, width=5, seed=3)).to_netcdf(day / "f3.nc", engine="h5netcdf")
    args = [f"--var={k}={v}" for k, v in MAPPING.items()]
    # The .npz files do not hold the mapped names, so they go in a call of their own.
    code, out, err = call_main(monkeypatch, capsys, "import-scan", day / "f3.nc", "--out", tmp_path / "out", *args)
    assert code == 0, err
    code, out2, err = call_main(monkeypatch, capsys, "import-scan", str(day / "f*.npz"), "--out", tmp_path / "out")
    assert code == 0, err
    lines = (out + out2).strip().splitlines()
    assert len(lines) == 3 and all("written to" in line for line in lines)
    stores = sorted(p.name for p in (tmp_path / "out").iterdir())
    assert stores == ["f1.scan.zarr", "f2.scan.zarr", "f3.scan.zarr"]
    for store in stores:
        scan = read_scan(tmp_path / "out" / store)
        assert scan.shape == (6, 5) and scan.has_geometry and scan.name == store.removesuffix(".scan.zarr")


def test_import_scan_cli__one_bad_file_writes_nothing(tmp_path, monkeypatch, capsys):
    day = tmp_path / "day"
    day.mkdir()
    save_npz(day / "a.npz", "a")
    np.savez(day / "b.npz", depth=np.ones((4, 6, 5), np.float32), frequencies_hz=np.asarray(FREQS))
    save_npz(day / "c.npz", "c")
    code, out, err = call_main(monkeypatch, capsys, "import-scan", day, "--out", tmp_path / "out")
    assert code == 2 and out == ""
    assert_one_error_line(err, "b.npz")
    assert not (tmp_path / "out").exists()


def test_import_scan_cli__single_store_and_user_errors(tmp_path, monkeypatch, capsys):
    save_npz(tmp_path / "one.npz", "one")
    code, out, _ = call_main(monkeypatch, capsys, "import-scan", tmp_path / "one.npz", "--out",
                             tmp_path / "x.scan.zarr")
    assert code == 0 and out.startswith("scan one: 6 x 5 pixels at 4 frequencies written to")
    assert read_scan(tmp_path / "x.scan.zarr").name == "one"
    save_npz(tmp_path / "two.npz", "two")
    for args, fragment in [
        ([tmp_path / "one.npz", "--out", tmp_path / "x.scan.zarr"], "already exists"),
        ([tmp_path / "one.npz", tmp_path / "two.npz", "--out", tmp_path / "y.scan.zarr"], "is one scan store"),
        ([tmp_path / "one.npz", "--out", tmp_path / "z.scan.zarr", "--var", "depth"], "NAME=VARIABLE"),
        ([tmp_path / "one.npz", "--out", tmp_path / "z.scan.zarr", "--var", "colour=c"], "not scan arrays"),
        ([tmp_path / "one.npz", "--out", tmp_path / "z.scan.zarr", "--frequencies", "a,b"], "--frequencies"),
        ([tmp_path / "nothing*.nc", "--out", tmp_path / "dir"], "matches no"),
    ]:
        code, out, err = call_main(monkeypatch, capsys, "import-scan", *args)
        assert code == 2 and out == "", args
        assert_one_error_line(err, fragment)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["one.npz", "two.npz", "x.scan.zarr"]
