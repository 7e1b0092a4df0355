"""Every command the README shows runs (small sizes): exit code 0 and its telling output line.

The commands of the README's command table run through :func:`mpi_lidar.cli.main` in this process, in the
order a user would chain them (simulate, tune, train, evaluate, ...), each on the previous one's outputs. A
README row without a case here fails the first test, so a documented command can never go untested again.
The README's own-scans block ("Correct your own scans") runs line by line, as written, on files prepared
the way it describes them.
"""

from __future__ import annotations

import functools
import re
import shlex
import subprocess
import sys
from pathlib import Path

import numpy as np
import optuna
import pytest

from mpi_lidar import cli
from mpi_lidar.config import Config
from mpi_lidar.scans.store import write_scan
from mpi_lidar.simulation.scenes import DEMO_SCENES, cornered_board, multi_object, render
from tests.cli_runner import call_main
from tests.model_factory import tiny_model

pytestmark = pytest.mark.integration

README = Path(__file__).resolve().parents[2] / "README.md"
ACTIVATE = "source .venv/bin/activate"
SMALL_CONFIG = "[dataset]\nsamples = 3000\nchunk_rows = 1500\nseed = 3\n"


def readme_shell_blocks() -> list[str]:
    """The ```bash blocks of the README."""
    return re.findall(r"```bash\n(.*?)```", README.read_text(), flags=re.S)


def own_scans_block() -> list[str]:
    """The command lines of the README's "Correct your own scans" block (each a ``mpi-lidar`` command), after the
    line that activates the environment, which the block starts with."""
    section = README.read_text().split("\n## Correct your own scans\n", 1)[1].split("\n## ", 1)[0]
    block = re.findall(r"```bash\n(.*?)```", section, flags=re.S)[0]
    lines = [line for line in block.splitlines() if line.strip()]
    assert lines[0] == ACTIVATE, "the block activates the environment before its first mpi-lidar command"
    return lines[1:]


def test_readme__activates_the_environment_before_the_first_mpi_lidar_command():
    text = README.read_text()
    assert text.index(ACTIVATE) < text.index("\nmpi-lidar ")
    venv = README.parent / ".venv" / "bin"
    assert (venv / "activate").is_file() and (venv / "mpi-lidar").is_file(), "what the line puts on the PATH"


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
    np.savez(root / "frame.npz", depth=depth, amplitude=rng.uniform(0.01, 0.03, depth.shape).astype(np.float32),
             frequencies_hz=np.asarray(config.frequencies_hz))
    # Two of the pipeline's demo scenes already in its run directory, as small scans (it keeps existing scans):
    # the pipeline renders the third itself and corrects all three.
    for number, scene in enumerate((cornered_board(height=30, width=40), multi_object(height=30, width=40))):
        write_scan(render(scene, config, np.random.default_rng(number)),
                   root / "run" / "scenes" / f"{scene.name}.scan.zarr")
    return root


def cases(w: Path) -> dict[str, tuple[list[str | Path], str]]:
    """Command -> (arguments, a fragment of a line its output must hold), in the order they run.

    The commands write where ``pipeline`` keeps its run (``run/``: dataset.zarr, optuna.db, model/), as a user
    chaining them would: the pipeline, last, resumes on them (the dataset, the study's trials and the model of
    its best parameters are kept) and adds the rest: evaluation, the demo scenes :func:`work` did not leave
    there, and the corrected scenes.
    """
    run = w / "run"
    data, model, scenes = run / "dataset.zarr", run / "model", w / "scenes"
    return {
        "simulate": (["simulate", "--out", data, "--config", w / "small.toml", "--workers", 0],
                     "chunks simulated"),
        "tune": (["tune", "--data", data, "--trials", 1, "--tune-rows", 1000, "--workers", 0],
                 "study 'xgboost'"),
        "train": (["train", "--data", data, "--out", model, "--study", "xgboost", "--workers", 0],
                  "model written to"),
        "evaluate": (["evaluate", "--data", data, "--model", model, "--out", w / "report"],
                     "report written to"),
        "render-scenes": (["render-scenes", "--out", scenes, "--scene", "flat_wall", "--scene",
                           "cornered_board"], "wrote"),
        "calibrate": (["calibrate", scenes / "cornered_board.scan.zarr", "--out", w / "sensor.toml"],
                      "sensor profile written to"),
        "correct": (["correct", scenes, "--model", model, "--out", w / "corrected", "--sensor",
                     w / "sensor.toml", "--workers", 0], "flat_wall"),
        "import-scan": (["import-scan", w / "frame.npz", "--out", w / "frame.scan.zarr"], "written to"),
        "verify": (["verify", data, w / "frame.scan.zarr"], "ok "),
        "table2": (["table2", "--data", data, "--out", w / "table2", "--trials", 1, "--train-rows", 500,
                    "--svm-rows", 200], "report written to"),
        "bench": (["bench", "--out", w / "bench", "--quick", "--rows", 200], "report written to"),
        "pipeline": (["pipeline", "--out", run, "--config", w / "small.toml", "--trials", 1,
                      "--tune-rows", 1000, "--workers", 0], "test split:"),
    }


def test_readme_table__every_command_has_a_case(tmp_path):
    documented = readme_commands()
    assert len(documented) >= 10
    assert sorted(documented) == sorted(cases(tmp_path))


def test_readme_shell_blocks__every_mpi_lidar_command_has_a_case(tmp_path):
    shown = {m for block in readme_shell_blocks() for m in re.findall(r"^mpi-lidar ([a-z0-9-]+)", block, flags=re.M)}
    assert shown and shown <= set(cases(tmp_path))


@pytest.mark.slow
def test_readme_own_scans_block__runs_as_written(tmp_path, monkeypatch, capsys):
    lines = own_scans_block()
    assert [shlex.split(line)[:2] for line in lines] == [["mpi-lidar", "import-scan"], ["mpi-lidar", "calibrate"],
                                                         ["mpi-lidar", "correct"], ["mpi-lidar", "verify"]]
    # what the README says raw/ holds: depth, amplitude, frequencies_hz and the scan grid (plus a reference)
    # (the cornered board of `mpi-lidar render-scenes`, on a grid of a quarter of its pixels)
    scan = render(cornered_board(height=60, width=80), Config(), np.random.default_rng(0))
    (tmp_path / "raw").mkdir()
    np.savez(tmp_path / "raw" / "corner.npz", depth=np.asarray(scan.depth), amplitude=np.asarray(scan.amplitude),
             frequencies_hz=np.asarray(scan.frequencies_hz), azimuth_rad=np.asarray(scan.azimuth_rad),
             elevation_rad=np.asarray(scan.elevation_rad), reference_depth=np.asarray(scan.reference_depth))
    tiny_model(tmp_path / "runs" / "quick" / "model")  # what `make run` leaves there
    monkeypatch.chdir(tmp_path)
    for line in lines:
        code, stdout, stderr = call_main(monkeypatch, capsys, *shlex.split(line)[1:])
        assert code == 0, f"{line}: exit {code}\n{stdout}\n{stderr}"
    outputs = tmp_path / "corrected" / "corner"
    for name in ("corrected.zarr", "metrics.json", "report.html", "corrected.laz", "corrected.ply", "raw.ply"):
        assert (outputs / name).exists(), name
    assert (tmp_path / "corrected" / "summary").is_dir()


@pytest.mark.slow
def test_readme_table__every_command_runs(work, monkeypatch, capsys):
    # The study's sampler seeded: its one trial, and the model of its parameters, take the same time every run
    # (unseeded, a learning rate drawn near 0.01 made tuning and training several times slower).
    monkeypatch.setattr(optuna.samplers, "TPESampler", functools.partial(optuna.samplers.TPESampler, seed=5))
    for name, (args, fragment) in cases(work).items():
        code, stdout, stderr = call_main(monkeypatch, capsys, *args)
        assert code == 0, f"{name}: exit {code}\n{stderr}"
        assert any(fragment in line for line in stdout.splitlines()), f"{name}: no line with {fragment!r}\n{stdout}"
    # the pipeline, last, resumed on what the commands before it left in its run directory
    assert "0 chunks written, 2 already there" in stdout and "0 trials run" in stdout, stdout
    assert f"model {work / 'run' / 'model'}: reused" in stdout, stdout
    assert all(f"scene {name}: " in stdout for name in DEMO_SCENES), stdout
    assert (work / "run" / "scenes" / "flat_wall.scan.zarr").is_dir(), "the demo scene that was missing is rendered"


@pytest.mark.slow
@pytest.mark.parametrize("command", [["benchmarks.sensor", "--rows", "2000", "--waveform-rows", "200", "--draws",
                                      "2000"],
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
