"""Faults of the machine: a full disk is one clear line (a user error, exit 2), never "unexpected"; the error
log in the temporary folder is this user's alone."""

from __future__ import annotations

import errno
import os
import stat
import subprocess
import tempfile
from collections.abc import Iterator
from pathlib import Path

import pytest

from mpi_lidar.errors import (
    EnvironmentFaultError,
    MpiLidarError,
    StoreError,
    environment_fault,
    write_error_log,
)
from mpi_lidar.scans.store import write_scan
from tests.cli_runner import assert_one_error_line, call_main
from tests.scan_factory import two_path_scan

pytestmark = pytest.mark.unit


def real_enospc() -> OSError:
    """The OSError a write to a full disk raises: /dev/full answers every write with ENOSPC."""
    try:
        with open("/dev/full", "wb", buffering=0) as full:
            full.write(b"x")
    except OSError as exc:
        return exc
    raise AssertionError("a write to /dev/full succeeded")


def test_environment_fault__a_real_full_disk_is_one_user_error_line():
    fault = environment_fault(real_enospc())
    assert isinstance(fault, EnvironmentFaultError) and isinstance(fault, MpiLidarError)
    assert fault.errno == errno.ENOSPC
    assert str(fault).startswith("the disk is full (ENOSPC)") and "\n" not in str(fault)
    assert "then run the command again" in str(fault)


def test_environment_fault__found_through_causes_contexts_and_groups():
    try:
        try:
            raise real_enospc()
        except OSError:
            raise RuntimeError("while writing the model") from None  # context kept, cause suppressed
    except RuntimeError as exc:
        in_context = exc
    assert environment_fault(in_context) is not None
    caused = StoreError("cannot write chunk 3")
    caused.__cause__ = real_enospc()
    assert environment_fault(caused) is not None
    assert environment_fault(ExceptionGroup("tasks", [ValueError("a"), caused])) is not None


def test_environment_fault__named_in_a_library_message_and_with_the_file():
    # XGBoost reports a full disk in its message only.
    assert environment_fault(RuntimeError("[01:02:03] model.ubj: No space left on device")) is not None
    named = environment_fault(OSError(errno.ENOSPC, os.strerror(errno.ENOSPC), "/data/out/model.ubj"))
    assert named is not None and "writing '/data/out/model.ubj'" in str(named)
    quota = environment_fault(OSError(errno.EDQUOT, os.strerror(errno.EDQUOT)))
    assert quota is not None and "quota" in str(quota)


@pytest.mark.parametrize("exc", [FileNotFoundError(errno.ENOENT, "No such file or directory", "x"),
                                 PermissionError(errno.EACCES, "Permission denied"), ValueError("no space here"),
                                 MemoryError()])
def test_environment_fault__other_errors_are_not_faults(exc):
    assert environment_fault(exc) is None


@pytest.fixture
def full_disk(tmp_path: Path) -> Iterator[Path]:
    """A real 64 KiB tmpfs (needs root's mount), torn down after the test."""
    mount = tmp_path / "tiny"
    mount.mkdir()
    made = subprocess.run(["mount", "-t", "tmpfs", "-o", "size=64k", "tmpfs", str(mount)], capture_output=True,
                          check=False)
    if made.returncode != 0:
        pytest.skip("no tmpfs can be mounted here (needs root); the /dev/full tests cover the mapping")
    try:
        yield mount
    finally:
        subprocess.run(["umount", "-l", str(mount)], check=False)


def fill(disk: Path) -> None:
    """Write to ``disk`` until it is full."""
    with pytest.raises(OSError) as full, open(disk / "filler", "wb") as filler:
        for _ in range(1 << 10):
            filler.write(b"\0" * (1 << 16))
            filler.flush()
    assert full.value.errno == errno.ENOSPC


def test_write_scan__a_full_disk_is_found_as_a_fault(full_disk):
    with pytest.raises(OSError) as raised:
        write_scan(two_path_scan("big", height=256, width=256), full_disk / "big.scan.zarr")
    fault = environment_fault(raised.value)
    assert fault is not None and fault.errno == errno.ENOSPC


def test_render_scenes__full_disk_is_one_line_exit_2(full_disk, monkeypatch, capsys):
    code, _, stderr = call_main(monkeypatch, capsys, "render-scenes", "--out", full_disk / "scenes", "--scene",
                                "flat_wall")
    assert code == 2
    assert_one_error_line(stderr)
    assert "No space left on device" in stderr or "the disk is full (ENOSPC)" in stderr


def test_write_error_log__private_to_this_user(tmp_path, monkeypatch):
    monkeypatch.setattr(tempfile, "tempdir", str(tmp_path))
    log = write_error_log("Traceback: postgresql://u:***@h/db")
    assert log is not None and log.read_text() == "Traceback: postgresql://u:***@h/db"
    assert stat.S_IMODE(log.stat().st_mode) == 0o600
    assert stat.S_IMODE(log.parent.stat().st_mode) == 0o700


def test_write_error_log__an_open_folder_is_closed_to_others(tmp_path, monkeypatch):
    monkeypatch.setattr(tempfile, "tempdir", str(tmp_path))
    folder = tmp_path / f"mpi-lidar-{os.getuid()}"
    folder.mkdir(mode=0o755)
    folder.chmod(0o755)
    assert write_error_log("traceback") == folder / "last-error.log"
    assert stat.S_IMODE(folder.stat().st_mode) == 0o700


def test_write_error_log__refuses_a_planted_link(tmp_path, monkeypatch):
    monkeypatch.setattr(tempfile, "tempdir", str(tmp_path))
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    (tmp_path / f"mpi-lidar-{os.getuid()}").symlink_to(elsewhere)
    assert write_error_log("secret traceback") is None
    assert list(elsewhere.iterdir()) == []


def test_write_error_log__a_full_disk_raises_nothing(full_disk, monkeypatch):
    monkeypatch.setattr(tempfile, "tempdir", str(full_disk))
    fill(full_disk)
    assert write_error_log("x" * (64 << 10)) is None


def test_environment_fault__xgboost_model_on_a_full_disk(full_disk):
    """XGBoost's writer reports a full disk as "FileStream.Write incomplete", without its errno."""
    import numpy as np
    import xgboost as xgb

    rows = np.random.default_rng(0).random((5000, 3))
    booster = xgb.train({"max_depth": 6, "nthread": 1}, xgb.DMatrix(rows, label=rows[:, 0]), 50)
    fill(full_disk)
    with pytest.raises(xgb.core.XGBoostError) as raised:
        booster.save_model(str(full_disk / "model.ubj"))
    fault = environment_fault(raised.value)
    assert fault is not None and fault.errno == errno.ENOSPC
    assert str(fault).startswith("a write was cut short (FileStream.Write incomplete), as on a full disk")
