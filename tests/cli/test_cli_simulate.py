"""``mpi-lidar simulate``: the store it writes, its summary, re-runs, and one-line errors with exit code 2.

The store cases run the installed console script as subprocesses. Each start costs ~3 s (dask, zarr and
distributed are imported before the configuration is checked), so the many input-error cases call the same
entry point, :func:`mpi_lidar.cli.main`, in this process, where the imports are paid once.
"""

from __future__ import annotations

import hashlib
import json
import re
import subprocess
import sys
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest
import xarray as xr

from mpi_lidar import cli
from mpi_lidar.config import Config, config_sha256, preset
from mpi_lidar.simulation import dataset
from tests.cli_runner import assert_one_error_line, call_main

SCRIPT = Path(sys.executable).with_name("mpi-lidar")
SAMPLES = 2_000
SEED = 5
ROW = re.compile(r"^([\d.]+) MHz +([\d.]+) +([\d.]+) +([\d.]+)$")  # a row of the plain table (piped)


def cli_command(*args: str | Path) -> list[str]:
    prefix = [str(SCRIPT)] if SCRIPT.exists() else [sys.executable, "-m", "mpi_lidar.cli"]
    return [*prefix, *map(str, args)]


def run_cli(*args: str | Path) -> subprocess.CompletedProcess[str]:
    return subprocess.run(cli_command(*args), capture_output=True, text=True, timeout=300)


def start_cli(*args: str | Path) -> subprocess.Popen[str]:
    return subprocess.Popen(cli_command(*args), stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)


def finish(process: subprocess.Popen[str]) -> subprocess.CompletedProcess[str]:
    stdout, stderr = process.communicate(timeout=300)
    return subprocess.CompletedProcess(process.args, process.returncode, stdout, stderr)


def snapshot(path: Path) -> dict[str, tuple[str, int]]:
    """Every file under path (or path itself) with its SHA-256 and modification time."""
    files = [path] if path.is_file() else sorted(p for p in path.rglob("*") if p.is_file())
    return {str(p.relative_to(path.parent)): (hashlib.sha256(p.read_bytes()).hexdigest(), p.stat().st_mtime_ns)
            for p in files}


def expected_config(seed: int = SEED) -> Config:
    """The paper preset's configuration at the test's size: its raw error is the calibration anchor."""
    return preset("paper").replace(dataset={"samples": SAMPLES, "chunk_rows": SAMPLES, "seed": seed})


@dataclass
class StoreRuns:
    """One store written by the CLI, then three runs started together against it and a foreign file."""

    out: Path
    first: subprocess.CompletedProcess[str]
    before: dict[str, tuple[str, int]]
    foreign: Path
    foreign_before: dict[str, tuple[str, int]]
    started: dict[str, subprocess.Popen[str]]

    def result(self, name: str) -> subprocess.CompletedProcess[str]:
        return finish(self.started[name])


@pytest.fixture(scope="module")
def runs(tmp_path_factory) -> Iterator[StoreRuns]:
    base = tmp_path_factory.mktemp("cli")
    out = base / "d.zarr"
    first = run_cli("simulate", "--out", out, "--preset", "paper", "--samples", SAMPLES, "--seed", SEED,
                    "--workers", 0)
    assert first.returncode == 0, first.stderr
    foreign = base / "notes.txt"
    foreign.write_text("precious\n")
    # each start costs seconds of imports: run the three independent ones at the same time
    before, foreign_before = snapshot(out), snapshot(foreign)
    started = {
        "rerun": start_cli("simulate", "--out", out, "--preset", "paper", "--samples", SAMPLES, "--seed", SEED,
                           "--workers", 0),
        "other_seed": start_cli("simulate", "--out", out, "--preset", "paper", "--samples", SAMPLES, "--seed",
                                SEED + 1, "--workers", 0),
        "regular_file": start_cli("simulate", "--out", foreign, "--samples", 100, "--workers", 0),
    }
    runs = StoreRuns(out, first, before, foreign, foreign_before, started)
    yield runs
    for process in started.values():
        if process.poll() is None:
            process.kill()
        process.communicate()


def summary_rows(stdout: str) -> dict[float, tuple[float, float, float]]:
    rows = {}
    for line in stdout.splitlines():
        match = ROW.match(line.strip())
        if match:
            f, mae, rmse, noise = map(float, match.groups())
            rows[f] = (mae, rmse, noise)
    return rows


@pytest.mark.integration
def test_simulate__writes_store_and_prints_summary(runs):
    out, result = runs.out, runs.first
    assert out.is_dir()
    rows = summary_rows(result.stdout)
    assert sorted(rows) == [12.5, 18.75, 25.0, 31.25]
    assert "raw MAE [mm]" in result.stdout and "noise-only MAE [mm]" in result.stdout
    assert "1 of 1 chunk simulated" in result.stdout
    # the printed numbers are the store's summary, in millimetres
    summary = dataset.summarize(out)
    for j, f in enumerate(summary.frequencies_hz):
        mae, _, noise = rows[f / 1e6]
        assert mae == pytest.approx(summary.mae_m[j] * 1e3, abs=1e-3)
        assert noise == pytest.approx(summary.noise_only_mae_m[j] * 1e3, abs=1e-3)
    # the calibration anchor of docs/results/sensor.md, with the wider tolerance of 2,000 rows
    assert rows[31.25][0] == pytest.approx(9.84, abs=1.5)
    assert rows[31.25][2] == pytest.approx(1.6, abs=0.3)
    assert all(rows[f][2] < rows[f][0] for f in rows)


@pytest.mark.integration
def test_simulate__store_opens_with_xarray_per_contract(runs):
    ds = xr.open_zarr(runs.out, consolidated=False)
    expected = {
        "features": (np.float32, ("sample", "feature"), (SAMPLES, 8)),
        "target": (np.float64, ("sample",), (SAMPLES,)),
        "theta": (np.float64, ("sample", "parameter"), (SAMPLES, 6)),
        "split": (np.uint8, ("sample",), (SAMPLES,)),
    }
    for name, (dtype, dims, shape) in expected.items():
        assert ds[name].dtype == dtype, name
        assert ds[name].dims == dims, name
        assert ds[name].shape == shape, name
    assert ds.attrs["schema"] == "mpi-lidar/dataset@1"
    assert ds.attrs["frequencies_hz"] == [12.5e6, 18.75e6, 25e6, 31.25e6]
    assert ds.attrs["config_sha256"] == config_sha256(expected_config())
    assert Config.model_validate(ds.attrs["config"]) == expected_config()
    assert "package_version" in ds.attrs
    assert ds["features"].attrs["columns"][:1] == ["depth_12.5MHz"]
    assert ds["features"].attrs["columns"][4:5] == ["amplitude_12.5MHz"]
    target = ds["target"].values
    np.testing.assert_array_equal(target, ds["theta"].values[:, 0])
    assert set(np.unique(ds["split"].values)) == {0, 1}
    # depth columns are near the truth (within centimetres), amplitudes positive
    features = ds["features"].values
    assert np.abs(features[:, :4] - target[:, None]).max() < 0.2
    assert np.all(features[:, 4:] > 0)
    json.dumps(ds.attrs["config"])  # plain JSON


@pytest.mark.integration
def test_simulate__rerun_on_same_store_writes_nothing(runs):
    again = runs.result("rerun")
    assert again.returncode == 0, again.stderr
    assert "0 of 1 chunk simulated" in again.stdout
    assert summary_rows(again.stdout) == summary_rows(runs.first.stdout)
    assert snapshot(runs.out) == runs.before


@pytest.mark.integration
def test_simulate__store_of_another_configuration_is_refused_unchanged(runs):
    other = runs.result("other_seed")
    assert other.returncode == 2
    assert_one_error_line(other.stderr, "another configuration")
    assert other.stdout == ""
    assert snapshot(runs.out) == runs.before


@pytest.mark.integration
def test_simulate__regular_file_at_out_is_refused_unchanged(runs):
    result = runs.result("regular_file")
    assert result.returncode == 2
    assert_one_error_line(result.stderr, "not a readable Zarr store")
    assert snapshot(runs.foreign) == runs.foreign_before
    assert sorted(p.name for p in runs.foreign.parent.iterdir()) == ["d.zarr", "notes.txt"]


# --- the other input errors, through the same entry point in this process -----------------------------------


BAD_CONFIGS = {
    "malformed": ("frequencies_hz = [1, 2\n", "is not valid TOML"),
    "unknown_scheme": ("[prior]\nscheme = \"uniform\"\n", "prior.scheme"),
    "zero_frequency": ("frequencies_hz = [0.0]\n", "frequencies_hz must be positive"),
    "negative_frequency": ("frequencies_hz = [12.5e6, -25e6]\n", "frequencies_hz must be positive"),
    "nyquist": ("frequencies_hz = [83.4e6]\n", "Nyquist"),
    "negative_distance": ("[prior]\nd_as_m = [-1.0, 2.0]\n", "d_as_m must be positive"),
    "rho_above_one": ("[prior]\nalbedo = [0.5, 1.5]\n", "albedo must lie in [0, 1]"),
    "unknown_field": ("[simulator]\nnoise = 0\n", "simulator.noise: unknown field"),
}


@pytest.mark.unit
@pytest.mark.parametrize("case", sorted(BAD_CONFIGS))
def test_simulate__bad_config_exits_2_with_one_line(tmp_path, monkeypatch, capsys, case):
    text, fragment = BAD_CONFIGS[case]
    config_file = tmp_path / "bad.toml"
    config_file.write_text(text)
    out = tmp_path / "d.zarr"
    code, stdout, stderr = call_main(monkeypatch, capsys, "simulate", "--out", out, "--config", config_file,
                                     "--samples", 100, "--workers", 0)
    assert code == 2
    assert_one_error_line(stderr, fragment)
    assert str(config_file) in stderr
    assert stdout == ""
    assert sorted(p.name for p in tmp_path.iterdir()) == ["bad.toml"]  # nothing at --out, no staging left


@pytest.mark.unit
def test_simulate__usage_error_is_one_line(tmp_path, monkeypatch, capsys):
    code, _, stderr = call_main(monkeypatch, capsys, "simulate", "--out", tmp_path / "d.zarr", "--samples", "many")
    assert code == 2
    assert_one_error_line(stderr, "invalid value for '--samples'")
    assert stderr.rstrip().endswith("(mpi-lidar simulate --help lists the options)")
    assert list(tmp_path.iterdir()) == []


@pytest.mark.unit
def test_simulate__missing_config_file(tmp_path, monkeypatch, capsys):
    code, _, stderr = call_main(monkeypatch, capsys, "simulate", "--out", tmp_path / "d.zarr",
                                "--config", tmp_path / "absent.toml", "--workers", 0)
    assert code == 2
    assert_one_error_line(stderr, "does not exist")
    assert list(tmp_path.iterdir()) == []


@pytest.mark.unit
def test_simulate__bad_command_line_override(tmp_path, monkeypatch, capsys):
    code, _, stderr = call_main(monkeypatch, capsys, "simulate", "--out", tmp_path / "d.zarr",
                                "--samples", 0, "--workers", 0)
    assert code == 2
    assert_one_error_line(stderr, "invalid value for '--samples': 0 is not in the range 1<=x")
    assert list(tmp_path.iterdir()) == []


@pytest.mark.unit
def test_simulate__non_empty_foreign_directory_is_refused_unchanged(tmp_path, monkeypatch, capsys):
    out = tmp_path / "photos"
    out.mkdir()
    (out / "holiday.jpg").write_bytes(b"\xff\xd8 not a zarr store")
    (out / "sub").mkdir()
    (out / "sub" / "notes.md").write_text("keep me\n")
    before = snapshot(out)
    code, _, stderr = call_main(monkeypatch, capsys, "simulate", "--out", out, "--samples", 100, "--workers", 0)
    assert code == 2
    assert_one_error_line(stderr, "not a readable Zarr store")
    assert snapshot(out) == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["photos"]


@pytest.mark.unit
def test_simulate__foreign_zarr_store_is_refused_unchanged(tmp_path, monkeypatch, capsys):
    import zarr

    out = tmp_path / "other.zarr"
    zarr.open_group(str(out), mode="w").attrs["schema"] = "someone-else@1"
    before = snapshot(out)
    code, _, stderr = call_main(monkeypatch, capsys, "simulate", "--out", out, "--samples", 100, "--workers", 0)
    assert code == 2
    assert_one_error_line(stderr, "is not an mpi-lidar dataset")
    assert snapshot(out) == before


@pytest.mark.unit
def test_simulate__empty_directory_is_used(tmp_path, monkeypatch, capsys):
    out = tmp_path / "empty"
    out.mkdir()
    monkeypatch.setattr(sys, "argv", ["mpi-lidar", "simulate", "--out", str(out), "--samples", "300",
                                      "--workers", "0"])
    cli.main()  # success returns without SystemExit
    captured = capsys.readouterr()
    assert "1 of 1 chunk simulated" in captured.out
    assert dataset.is_complete(out)


@pytest.mark.integration
def test_simulate_cli__sensor_profile_sets_frequencies_noise_and_working_range(tmp_path, monkeypatch, capsys):
    profile = tmp_path / "sensor.toml"
    profile.write_text('schema = "mpi-lidar/sensor@1"\nfootprint_area_m2 = 0.02\nnoise_scale = 2.0\n'
                       "frequencies_hz = [10000000.0, 20000000.0, 30000000.0]\nrange_m = [1.0, 6.0]\n")
    code, out, err = call_main(monkeypatch, capsys, "simulate", "--out", tmp_path / "d.zarr", "--samples", "400",
                               "--workers", "0", "--sensor", profile)
    assert code == 0, err
    config = dataset.store_config(dataset.open_store(tmp_path / "d.zarr"))
    assert config.frequencies_hz == (10e6, 20e6, 30e6) and config.simulator.noise_scale == 2.0
    assert config.prior.d_as_m == pytest.approx((0.85, 6.9)) and config.prior.d_as_distribution == "log_uniform"
    assert "10 MHz" in out and "30 MHz" in out
    profile.write_text('schema = "mpi-lidar/sensor@1"\nfootprint_area_m2 = 0.02\nfrequencies_hz = [1e9]\n')
    code, out, err = call_main(monkeypatch, capsys, "simulate", "--out", tmp_path / "e.zarr", "--samples", "400",
                               "--workers", "0", "--sensor", profile)
    assert code == 2 and str(profile) in err and "cannot be demodulated" in err
    assert_one_error_line(err)
    assert not (tmp_path / "e.zarr").exists()
