"""The command line called in this process, as a user's shell would, and the one-error-line check."""

from __future__ import annotations

import sys
from pathlib import Path

import pytest

from mpi_lidar import cli


def call_main(monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str],
              *args: str | Path) -> tuple[int, str, str]:
    """Run ``mpi-lidar ARGS`` through :func:`mpi_lidar.cli.main`; its exit code, stdout and stderr."""
    monkeypatch.setattr(sys, "argv", ["mpi-lidar", *map(str, args)])
    try:
        cli.main()
        code = 0
    except SystemExit as exc:
        code = exc.code or 0
    captured = capsys.readouterr()
    return code, captured.out, captured.err


def assert_one_error_line(stderr: str, fragment: str = "") -> None:
    """stderr is exactly one ``error:`` line (no traceback), holding ``fragment``."""
    lines = stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: "), stderr
    assert fragment in lines[0], stderr
