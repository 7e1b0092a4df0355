"""Standard error holds error lines only: the command line run as a user runs it, in a subprocess, piped.

A usage error, a missing path and a batch of scans with infinite depths each leave exactly what the README
promises on stderr (one ``error:`` line, or nothing); piped output has no markdown and shows progress lines.
"""

from __future__ import annotations

import os
import subprocess
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from mpi_lidar.scans.store import write_scan
from tests.model_factory import tiny_model
from tests.scan_factory import two_path_scan

pytestmark = pytest.mark.integration

ROOT = Path(__file__).resolve().parents[1]


def run_cli(*args: str | Path, cwd: Path, env: dict[str, str] | None = None) -> subprocess.CompletedProcess[str]:
    """``mpi-lidar ARGS`` in a subprocess, stdout and stderr piped (not a terminal)."""
    return subprocess.run([sys.executable, "-m", "mpi_lidar.cli", *map(str, args)], capture_output=True, text=True,
                          cwd=cwd, timeout=300, env={**os.environ, **(env or {}), "PYTHONPATH": str(ROOT)})


def one_error_line(stderr: str) -> str:
    lines = stderr.splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: "), stderr
    return lines[0]


@pytest.fixture(scope="module")
def batch(tmp_path_factory) -> Path:
    """A tiny model and three scans, one of them with infinite and huge depths (given as unwrapped: a wrapped scan's
    depth past its wrap period is refused when it is written)."""
    root = tmp_path_factory.mktemp("quiet")
    tiny_model(root / "model", rounds=5, rows=1_000)
    for index in range(3):
        scan = two_path_scan(f"scan_{index}", height=12, width=16, seed=index)
        if index == 1:
            scan.depth[:, 0, :4] = np.inf
            scan.depth[:, 1, :4] = 3e38
            scan = replace(scan, depth_wrapped=False)
        write_scan(scan, root / "scans" / f"scan_{index}.scan.zarr")
    return root


def test_correct_cli__a_mistyped_option_is_one_line_exit_2(tmp_path):
    result = run_cli("correct", "scans", "--model", "m", "--out", "o", "--frobnicate", cwd=tmp_path)
    assert result.returncode == 2
    line = one_error_line(result.stderr)
    assert "no such option --frobnicate (" in line and "mpi-lidar correct --help" in line, line
    assert "Usage:" not in result.stderr and result.stdout == ""
    assert not (tmp_path / "o").exists()


def test_correct_cli__a_missing_scan_is_one_line_exit_2_nothing_written(batch, tmp_path):
    result = run_cli("correct", tmp_path / "missing.scan.zarr", "--model", batch / "model", "--out", tmp_path / "o",
                     cwd=tmp_path)
    assert result.returncode == 2, result.stderr
    assert "missing.scan.zarr" in one_error_line(result.stderr)
    assert not (tmp_path / "o").exists()


def test_correct_cli__a_refused_batch_shows_no_progress_line(batch, tmp_path):
    result = run_cli("correct", batch / "scans", "--model", tmp_path / "no-model", "--out", tmp_path / "o",
                     cwd=tmp_path)
    assert result.returncode == 2, result.stderr
    one_error_line(result.stderr)
    assert "correcting scans" not in result.stdout, result.stdout


@pytest.mark.slow
def test_correct_cli__piped_shows_progress_lines_plain_tables_and_a_quiet_stderr(batch, tmp_path):
    result = run_cli("correct", batch / "scans", "--model", batch / "model", "--out", tmp_path / "out",
                     "--allow-unserved", cwd=tmp_path)
    assert result.returncode in (0, 1), result.stderr
    # nothing on stderr but error lines: no RuntimeWarning from the infinite and huge depths, no log lines
    assert all(line.startswith("error: ") for line in result.stderr.splitlines()), result.stderr
    assert "Warning" not in result.stderr
    lines = result.stdout.splitlines()
    progress = [line for line in lines if line.startswith("correcting scans: ")]
    assert progress[0] != "correcting scans: 0/3" and progress[-1].startswith("correcting scans: 3/3")
    assert len(progress) <= 3  # a few seconds: the start and the end, one line per 20 s at most between
    assert "|---" not in result.stdout and "](" not in result.stdout and "| scan |" not in result.stdout
    assert any(line.startswith("3 scans in ") for line in lines), result.stdout
    header = next(line for line in lines if line.startswith("scan "))
    assert header.split()[:2] == ["scan", "status"]
    assert all(any(line.startswith(f"scan_{i} ") for line in lines) for i in range(3)), result.stdout
    assert (tmp_path / "out" / "summary" / "report.md").read_text().count("\n|---") == 1  # markdown: in files


def test_cli__without_debug_asyncio_teardown_errors_stay_off_stderr(tmp_path):
    # What a Dask client torn down after an error leaves: a task still pending when its loop goes.
    script = ("import asyncio, gc, sys\n"
              "from mpi_lidar import cli\n"
              "if sys.argv[1] == 'quiet':\n"
              "    cli._quiet()\n"
              "async def forever():\n"
              "    await asyncio.sleep(3600)\n"
              "loop = asyncio.new_event_loop()\n"
              "task = loop.create_task(forever())\n"
              "loop.run_until_complete(asyncio.sleep(0))\n"
              "loop.close()\n"
              "del task\n"
              "gc.collect()\n"
              "import numpy as np\n"
              "np.float32(3e38) * np.float32(10)\n")
    env = {name: value for name, value in os.environ.items() if name != "PYTHONWARNINGS"}
    loud, quiet = (subprocess.run([sys.executable, "-c", script, mode], capture_output=True, text=True, cwd=ROOT,
                                  timeout=60, env=env) for mode in ("loud", "quiet"))
    assert "Task was destroyed" in loud.stderr and "RuntimeWarning" in loud.stderr  # what the user saw before
    assert quiet.returncode == 0 and quiet.stderr == ""


@pytest.mark.slow
def test_train_cli__xgboost_says_nothing_on_stderr(tmp_path):
    # Training through xgboost.dask joins its workers; each one's native "Task ... got rank N" line went to stderr.
    (tmp_path / "small.toml").write_text("[dataset]\nsamples = 2000\nchunk_rows = 2000\nseed = 3\n")
    simulated = run_cli("simulate", "--out", "d.zarr", "--config", "small.toml", "--workers", "0", cwd=tmp_path)
    assert simulated.returncode == 0 and simulated.stderr == "", simulated.stderr
    assert "|---" not in simulated.stdout and "frequency" in simulated.stdout  # its table, plain
    (tmp_path / "params.json").write_text('{"max_depth": 3, "learning_rate": 0.3}')
    trained = run_cli("train", "--data", "d.zarr", "--out", "model", "--params", "params.json", "--workers", "0",
                      cwd=tmp_path)
    assert trained.returncode == 0, trained.stderr
    assert trained.stderr == ""
    lines = trained.stdout.splitlines()
    assert lines[0].startswith("training on d.zarr") and lines[-1].startswith("model written to model: ")
