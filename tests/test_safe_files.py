"""Configuration inputs are read only from regular files of at most 1 MiB: devices, FIFOs, directories and
links to them are refused at once, with one line, and a command that was given one writes nothing."""

from __future__ import annotations

import os
import signal
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path

import pytest

from mpi_lidar.calibration.profile import read_profile
from mpi_lidar.config import load_config
from mpi_lidar.errors import ConfigError, MpiLidarError
from mpi_lidar.safe_files import MAX_CONFIG_BYTES, read_small_bytes, read_small_text, regular_file_size
from tests.cli_runner import assert_one_error_line, call_main

pytestmark = pytest.mark.unit

READERS: dict[str, Callable[[Path], object]] = {
    "config file": load_config,
    "sensor profile": read_profile,
    "parameter file": lambda path: read_small_text(path, "parameter file"),
}
REFUSAL_S = 2.0  # a refusal reads nothing: far less than this


@contextmanager
def deadline(seconds: float) -> Iterator[None]:
    """Raise TimeoutError in this (the main) thread if the block takes longer: a hang fails, never blocks."""
    def expire(signum: int, frame: object) -> None:
        raise TimeoutError(f"still reading after {seconds} s")

    previous = signal.signal(signal.SIGALRM, expire)
    signal.setitimer(signal.ITIMER_REAL, seconds)
    try:
        yield
    finally:
        signal.setitimer(signal.ITIMER_REAL, 0)
        signal.signal(signal.SIGALRM, previous)


@pytest.fixture
def fifo(tmp_path: Path) -> Path:
    path = tmp_path / "sensor.toml"
    os.mkfifo(path)
    return path


def special_files(tmp_path: Path) -> dict[str, Path]:
    fifo = tmp_path / "pipe.toml"
    os.mkfifo(fifo)
    link = tmp_path / "zero.toml"
    link.symlink_to("/dev/zero")
    folder = tmp_path / "folder.toml"
    folder.mkdir()
    return {"FIFO": fifo, "/dev/zero": Path("/dev/zero"), "link to /dev/zero": link, "directory": folder,
            "/dev/null": Path("/dev/null")}


@pytest.mark.parametrize("what", sorted(READERS))
def test_readers__refuse_anything_but_a_regular_file_at_once(tmp_path, what):
    for kind, path in special_files(tmp_path).items():
        with deadline(REFUSAL_S), pytest.raises(MpiLidarError) as refused:
            READERS[what](path)
        message = str(refused.value)
        assert "\n" not in message and str(path) in message, (kind, message)
        assert "regular file" in message or "directory" in message, (kind, message)


@pytest.mark.parametrize("what", sorted(READERS))
def test_readers__refuse_a_file_past_the_size_limit_before_reading_it(tmp_path, what):
    path = tmp_path / "big.toml"
    path.write_bytes(b"# " + b"x" * MAX_CONFIG_BYTES)
    with pytest.raises(MpiLidarError, match=f"more than the {MAX_CONFIG_BYTES:,}"):
        READERS[what](path)


def test_read_small_bytes__limit_is_inclusive(tmp_path):
    path = tmp_path / "ten"
    path.write_bytes(b"0123456789")
    assert read_small_bytes(path, "file", limit=10) == b"0123456789"
    with pytest.raises(ConfigError, match="10 bytes, more than the 9"):
        read_small_bytes(path, "file", limit=9)


def test_read_small_text__refuses_text_that_is_not_utf8(tmp_path):
    path = tmp_path / "latin1.toml"
    path.write_bytes(b"name = \"caf\xe9\"\n")
    with pytest.raises(ConfigError, match=r"is not valid UTF-8 text: byte 11 \(b'\\xe9'\) is not UTF-8"):
        read_small_text(path, "config file")
    with pytest.raises(ConfigError, match="is not valid TOML: byte 11"):
        load_config(path)


def test_read_small_text__a_link_to_a_regular_file_is_read(tmp_path):
    target = tmp_path / "real.toml"
    target.write_text("[dataset]\nsamples = 100\nchunk_rows = 50\n")
    link = tmp_path / "link.toml"
    link.symlink_to(target)
    assert load_config(link).dataset.samples == 100


def test_read_small_text__missing_and_unreadable(tmp_path):
    with pytest.raises(ConfigError, match="does not exist"):
        read_small_text(tmp_path / "none.toml", "config file")
    if os.getuid() != 0:  # root reads any file
        locked = tmp_path / "locked.toml"
        locked.write_text("x = 1\n")
        locked.chmod(0)
        with pytest.raises(ConfigError, match="cannot be read"):
            read_small_text(locked, "config file")


@pytest.mark.parametrize("option", ["--config", "--sensor"])
def test_simulate__config_or_sensor_from_a_fifo_or_dev_zero_is_one_line_and_writes_nothing(
        tmp_path, monkeypatch, capsys, fifo, option):
    for source in (fifo, Path("/dev/zero")):
        out = tmp_path / "d.zarr"
        with deadline(30):  # the command line imports its modules first; the refusal itself is instant
            code, _, stderr = call_main(monkeypatch, capsys, "simulate", "--out", out, option, source,
                                        "--samples", 50, "--workers", 0)
        assert code == 2
        assert_one_error_line(stderr, str(source))
        assert not out.exists()


def test_regular_file_size__refuses_before_opening_and_measures_a_file(tmp_path):
    for path in special_files(tmp_path).values():
        with deadline(REFUSAL_S), pytest.raises(ConfigError, match=r"regular file|directory"):
            regular_file_size(path, "scan file")
    path = tmp_path / "scan.npz"
    path.write_bytes(b"x" * 100)
    assert regular_file_size(path, "scan file") == 100
    assert regular_file_size(path, "scan file", limit=100) == 100
    with pytest.raises(ConfigError, match="100 bytes, more than the 99"):
        regular_file_size(path, "scan file", limit=99)
