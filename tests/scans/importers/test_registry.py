"""The importer registry and the batch import (mpi_lidar.scans.importers), through the CLI too."""

from __future__ import annotations

import numpy as np
import pytest

from mpi_lidar.scans.importers import IMPORT_SUFFIXES, IMPORTERS, find_scan_files, importer_for, plan_import
from mpi_lidar.scans.importers.base import ScanImporter
from mpi_lidar.scans.scan import ScanError
from mpi_lidar.scans.store import read_scan
from tests.cli_runner import assert_one_error_line, call_main
from tests.scan_factory import two_path_scan
from tests.scans.importers.files import FREQS, MAPPING, save_npz, tool_dataset


@pytest.mark.unit
def test_importers__one_per_format_each_suffix_once(tmp_path):
    assert IMPORT_SUFFIXES == (".npz", ".nc", ".h5", ".hdf5", ".zarr")
    assert all(isinstance(importer, ScanImporter) for importer in IMPORTERS)
    assert importer_for(tmp_path / "A.NPZ") is IMPORTERS[0] and importer_for(tmp_path / "a.hdf5") is IMPORTERS[1]
    assert importer_for(tmp_path / "a.txt") is None
    with pytest.raises(ScanError, match=r"cannot import \.txt; give \.npz, \.nc, \.h5, \.hdf5, \.zarr"):
        from mpi_lidar.scans.importers import load_scan_file

        load_scan_file(tmp_path / "a.txt", FREQS)

@pytest.mark.unit
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


@pytest.mark.integration
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


@pytest.mark.integration
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


@pytest.mark.integration
def test_import_scan_cli__single_store_and_user_errors(tmp_path, monkeypatch, capsys):
    save_npz(tmp_path / "one.npz", "one")
    code, out, _ = call_main(monkeypatch, capsys, "import-scan", tmp_path / "one.npz", "--out",
                             tmp_path / "x.scan.zarr")
    assert code == 0 and out.startswith("scan one: 6 x 5 pixels at 4 frequencies (c = 299792458 m/s) written to")
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


@pytest.mark.integration
def test_import_scan_cli__more_files_join_an_import_directory(tmp_path, monkeypatch, capsys):
    day = tmp_path / "day"
    day.mkdir()
    save_npz(day / "a.npz", "a")
    code, _, err = call_main(monkeypatch, capsys, "import-scan", day, "--out", tmp_path / "out")
    assert code == 0, err
    first = (tmp_path / "out" / "a.scan.zarr" / "zarr.json").stat().st_mtime_ns
    save_npz(day / "b.npz", "b", seed=1)
    code, out, err = call_main(monkeypatch, capsys, "import-scan", str(day / "*.npz"), "--out", tmp_path / "out")
    assert code == 0, err
    assert "scan b:" in out and "scan a:" not in out
    assert err.count("\n") == 1 and "a.npz (a.scan.zarr)" in err and "b.npz" not in err
    assert sorted(p.name for p in (tmp_path / "out").iterdir()) == ["a.scan.zarr", "b.scan.zarr"]
    assert (tmp_path / "out" / "a.scan.zarr" / "zarr.json").stat().st_mtime_ns == first
    code, out, err = call_main(monkeypatch, capsys, "import-scan", day, "--out", tmp_path / "out")
    assert code == 2 and out == ""
    assert_one_error_line(err, "a.scan.zarr already exists (and the 1 others')")


@pytest.mark.integration
def test_import_scan_cli__frequencies_in_mhz_are_refused_before_anything_is_read(tmp_path, monkeypatch, capsys):
    save_npz(tmp_path / "a.npz", "a")
    code, out, err = call_main(monkeypatch, capsys, "import-scan", tmp_path / "a.npz",
                               "--out", tmp_path / "a.scan.zarr", "--frequencies", "12.5,18.75,25,31.25")
    assert code == 2 and out == ""
    assert_one_error_line(err, "12.5 MHz is 1.25e+07")
    assert not (tmp_path / "a.scan.zarr").exists()
    np.savez(tmp_path / "b.npz", depth=np.ones((4, 6, 5), np.float32), amplitude=np.ones((4, 6, 5), np.float32),
             frequencies_hz=np.asarray(FREQS) / 1e6)
    code, out, err = call_main(monkeypatch, capsys, "import-scan", tmp_path / "b.npz",
                               "--out", tmp_path / "b.scan.zarr")
    assert code == 2 and "b.npz" in err and "frequencies are in Hz" in err


@pytest.mark.integration
def test_import_scan_cli__depths_wrapped_or_unwrapped_are_recorded(tmp_path, monkeypatch, capsys):
    save_npz(tmp_path / "a.npz", "a")
    for depths in ("wrapped", "unwrapped"):
        store = tmp_path / f"{depths}.scan.zarr"
        code, _, err = call_main(monkeypatch, capsys, "import-scan", tmp_path / "a.npz", "--out", store,
                                 "--depths", depths)
        assert code == 0, err
        assert read_scan(store).depth_wrapped is (depths == "wrapped")
    wrapped, unwrapped = (read_scan(tmp_path / f"{d}.scan.zarr") for d in ("wrapped", "unwrapped"))
    assert wrapped.content_sha256() != unwrapped.content_sha256(), "the convention is part of what correction reads"
