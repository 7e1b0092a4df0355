"""What import-scan opens (regular files within a size limit, checked before any read) and what it leaves
(all of its stores or none) (mpi_lidar.scans.importers)."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

from mpi_lidar.scans.importers import MAX_FILE_BYTES, find_scan_files, import_files, load_scan_file, plan_import
from mpi_lidar.scans.scan import ScanError
from mpi_lidar.scans.store import read_scan
from tests.cli_runner import assert_one_error_line, call_main
from tests.scans.importers.files import save_npz


@pytest.mark.unit
def test_find_scan_files__a_fifo_is_refused_before_it_is_opened(tmp_path):
    os.mkfifo(tmp_path / "pipe.npz")  # opening it for reading would block until a writer comes
    save_npz(tmp_path / "a.npz")
    for source in (tmp_path / "pipe.npz", tmp_path, str(tmp_path / "*.npz")):
        with pytest.raises(ScanError, match=r"pipe\.npz is a FIFO \(named pipe\), not a regular file"):
            find_scan_files([source])
    with pytest.raises(ScanError, match="not a regular file"):
        load_scan_file(tmp_path / "pipe.npz")


@pytest.mark.unit
@pytest.mark.skipif(not Path("/dev/zero").exists(), reason="needs /dev/zero")
def test_find_scan_files__a_link_to_a_device_is_refused(tmp_path):
    (tmp_path / "zero.nc").symlink_to("/dev/zero")
    with pytest.raises(ScanError, match=r"zero\.nc is, through a symbolic link, a device, not a regular file"):
        find_scan_files([tmp_path / "zero.nc"])
    with pytest.raises(ScanError, match="not a regular file"):
        load_scan_file(tmp_path / "zero.nc")
    (tmp_path / "folder.h5").mkdir()
    with pytest.raises(ScanError, match=r"folder\.h5 is a directory, not a regular file"):
        find_scan_files([str(tmp_path / "folder.*")])


@pytest.mark.unit
def test_find_scan_files__a_file_over_the_limit_is_refused_unread(tmp_path):
    big = tmp_path / "big.npz"
    with big.open("wb") as stream:
        stream.truncate(MAX_FILE_BYTES + 1)  # sparse: takes no disk
    with pytest.raises(ScanError, match=r"big\.npz is 2\.0 GiB, more than the 2 GiB an imported file may be"):
        find_scan_files([big])
    with pytest.raises(ScanError, match="more than the 2 GiB"):
        load_scan_file(big)


@pytest.mark.unit
def test_import_files__a_failing_second_store_leaves_the_first_unwritten(tmp_path):
    a, b = save_npz(tmp_path / "a.npz", "a"), save_npz(tmp_path / "b.npz", "b")
    (tmp_path / "blocker").write_text("a file where the second store's directory should be")
    plan = [(a, tmp_path / "out" / "a.scan.zarr"), (b, tmp_path / "blocker" / "b.scan.zarr")]
    with pytest.raises(ScanError, match=r"blocker/b\.scan\.zarr") as error:
        import_files(plan)
    assert ".writing-" not in str(error.value), "the error names the store asked for, not its staging name"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.npz", "b.npz", "blocker"]  # out/ removed too


@pytest.mark.unit
def test_import_files__a_target_that_appears_undoes_the_renamed_stores(tmp_path):
    a, b = save_npz(tmp_path / "a.npz", "a"), save_npz(tmp_path / "b.npz", "b")
    out = tmp_path / "out"
    out.mkdir()
    # Both pairs name one store: the first is renamed into place, the second finds it there.
    with pytest.raises(ScanError, match=r"one\.scan\.zarr appeared while importing; nothing was imported"):
        import_files([(a, out / "one.scan.zarr"), (b, out / "one.scan.zarr")])
    assert list(out.iterdir()) == []  # neither the store nor a staging directory


@pytest.mark.unit
def test_import_files__all_stores_appear_together(tmp_path):
    day = tmp_path / "day"
    day.mkdir()
    for name in ("a", "b", "c"):
        save_npz(day / f"{name}.npz", name)
    seen: list[tuple[str, bool]] = []
    written = import_files(plan_import(find_scan_files([day]), tmp_path / "out"),
                           on_scan=lambda scan, target: seen.append((scan.name, target.exists())))
    assert [p.name for p in written] == ["a.scan.zarr", "b.scan.zarr", "c.scan.zarr"]
    assert seen == [("a", True), ("b", True), ("c", True)], "on_scan runs once every store is in place"
    assert sorted(p.name for p in (tmp_path / "out").iterdir()) == ["a.scan.zarr", "b.scan.zarr", "c.scan.zarr"]
    assert read_scan(written[1]).name == "b"


@pytest.mark.integration
def test_import_scan_cli__a_fifo_is_one_error_line(tmp_path, monkeypatch, capsys):
    os.mkfifo(tmp_path / "live.nc")
    code, out, err = call_main(monkeypatch, capsys, "import-scan", tmp_path / "live.nc", "--out", tmp_path / "o")
    assert code == 2 and out == ""
    assert_one_error_line(err, "is a FIFO (named pipe), not a regular file")
    assert not (tmp_path / "o").exists()
