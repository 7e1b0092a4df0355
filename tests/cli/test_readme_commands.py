"""Every command of the README's command table runs (small sizes): exit code 0 and its telling output line.

The commands run through :func:`mpi_lidar.cli.main` in this process, in the order a user would chain them
(simulate, tune, train, evaluate, ...), each on the previous one's outputs. A README row without a case here
fails the first test, so a documented command can never go untested again.
"""

from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from mpi_lidar import cli
from mpi_lidar.config import Config
from tests.cli_runner import call_main

README = Path(__file__).resolve().parents[2] / "README.md"
SMALL_CONFIG = "[dataset]\nsamples = 3000\nchunk_rows = 1500\nseed = 3\n"


def readme_commands() -> list[str]:
    """The sub-command of every row of the README's command table (``| `mpi-lidar NAME ...` | ... |``)."""
    return re.findall(r"^\| `mpi-lidar ([a-z0-9-]+)", README.read_text(), flags=re.M)


@pytest.fixture(scope="module")
def work(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("readme")
    (root / "small.toml").write_text(SMALL_CONFIG)
    config = Config()
    rng = np.random.default_rng(0)
    depth = rng.uniform(1.5, 2.0, (4, 5, 6)).astype(np.float32)
    np.savez(root / "frame.npz", depth=depth, amplitude=np.full_like(depth, 0.02),
             frequencies_hz=np.asarray(config.frequencies_hz))
    return root


def cases(w: Path) -> dict[str, tuple[list[str | Path], str]]:
    """Command -> (arguments, a fragment of a line its output must hold), in the order they run."""
    return {
        "simulate": (["simulate", "--out", w / "d.zarr", "--config", w / "small.toml", "--workers", 0],
                     "chunks simulated"),
        "tune": (["tune", "--data", w / "d.zarr", "--trials", 2, "--tune-rows", 1000, "--workers", 0],
                 "study 'xgboost'"),
        "train": (["train", "--data", w / "d.zarr", "--out", w / "model", "--study", "xgboost", "--workers", 0],
                  "model written to"),
        "evaluate": (["evaluate", "--data", w / "d.zarr", "--model", w / "model", "--out", w / "report"],
                     "report written to"),
        "render-scenes": (["render-scenes", "--out", w / "scenes", "--scene", "flat_wall", "--scene",
                           "cornered_board"], "wrote"),
        "calibrate": (["calibrate", w / "scenes" / "cornered_board.scan.zarr", "--out", w / "sensor.toml"],
                      "sensor profile written to"),
        "correct": (["correct", w / "scenes", "--model", w / "model", "--out", w / "corrected", "--sensor",
                     w / "sensor.toml", "--workers", 0], "flat_wall"),
        "import-scan": (["import-scan", w / "frame.npz", "--out", w / "frame.scan.zarr"], "written to"),
        "verify": (["verify", w / "d.zarr", w / "frame.scan.zarr"], "ok "),
        "table2": (["table2", "--data", w / "d.zarr", "--out", w / "table2", "--trials", 1, "--train-rows", 500,
                    "--svm-rows", 200], "report written to"),
        "bench": (["bench", "--out", w / "bench", "--quick"], "report written to"),
        "pipeline": (["pipeline", "--out", w / "run", "--config", w / "small.toml", "--trials", 1,
                      "--tune-rows", 1000, "--workers", 0], "test split:"),
    }


def test_readme_table__every_command_has_a_case(tmp_path):
    documented = readme_commands()
    assert len(documented) >= 10
    assert sorted(documented) == sorted(cases(tmp_path))


@pytest.mark.slow
def test_readme_table__every_command_runs(work, monkeypatch, capsys):
    for name, (args, fragment) in cases(work).items():
        code, stdout, stderr = call_main(monkeypatch, capsys, *args)
        assert code == 0, f"{name}: exit {code}\n{stderr}"
        assert any(fragment in line for line in stdout.splitlines()), f"{name}: no line with {fragment!r}\n{stdout}"


@pytest.mark.parametrize("command", [["benchmarks.sensor", "--rows", "2000"],
                                     ["benchmarks.limits", "--n-test", "20", "--pool", "100", "--scales", "1"]])
def test_readme_benchmark_commands__run_small(command):
    result = subprocess.run([sys.executable, "-m", *command], capture_output=True, text=True, timeout=300,
                            cwd=README.parent)
    assert result.returncode == 0, result.stderr
    assert "|" in result.stdout  # a markdown table


def test_help__every_command_shows_an_example(monkeypatch, capsys):
    for name in sorted(cli.cli.commands):
        code, stdout, _ = call_main(monkeypatch, capsys, name, "--help")
        assert code == 0 and "Example:" in stdout and f"mpi-lidar {name}" in stdout, name
