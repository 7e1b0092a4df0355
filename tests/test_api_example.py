"""The README's Python API example on the scans a new user brings: wrapped depths (a corner at 6 m) and amplitudes in
a scanner's counts. Its point fields come from ``mpi_lidar.point_cloud_fields``, as the command line's files do."""

from __future__ import annotations

import re
from dataclasses import replace
from pathlib import Path

import laspy
import numpy as np
import pytest

import mpi_lidar
from mpi_lidar.config import Config, PriorConfig
from mpi_lidar.learning.model import load_model
from mpi_lidar.reporting.point_cloud_files import write_point_clouds
from mpi_lidar.scans.pointcloud import PointCloudFormat
from mpi_lidar.scans.store import write_scan
from mpi_lidar.simulation.scenes import corner, render
from tests.model_factory import tiny_model
from tests.test_api import README, readme_python_example

pytestmark = [pytest.mark.integration, pytest.mark.slow]


def _example_fields(tmp_path: Path, monkeypatch, scan, options: str) -> laspy.LasData:
    """The README example run on ``scan`` with ``options`` (Python source) given to ``correct_scan``; its LAZ."""
    code = readme_python_example()
    model_dir = re.search(r'load_model\("([^"]+)"\)', code).group(1)
    scan_path = re.search(r'read_scan\("([^"]+)"\)', code).group(1)
    output = re.search(r'write_point_cloud\("([^"]+)"', code).group(1)
    call = re.search(r"mpi_lidar\.correct_scan\(scan, model\)", code)
    assert call, "the example corrects with correct_scan(scan, model)"
    code = code.replace(call.group(0), f"mpi_lidar.correct_scan(scan, model, {options})")
    tiny_model(tmp_path / model_dir, geometric=False, feature_set="raw", rounds=5,
               config=Config(prior=PriorConfig(d_as_m=(0.5, 8.0))))
    write_scan(replace(scan, name=Path(scan_path).name.removesuffix(".scan.zarr")), tmp_path / scan_path)
    monkeypatch.chdir(tmp_path)
    exec(compile(code, str(README), "exec"), {})
    return laspy.read(tmp_path / output)


def test_readme_python_example__wrapped_corner_at_6_m_gets_unwrapped_ranges(tmp_path, monkeypatch, capsys):
    scan = render(corner(distance_m=6.0, height=16, width=24), Config(), np.random.default_rng(6))
    assert np.nanmax(scan.depth[-1]) < 4.8, "the 31.25 MHz depths wrap"
    las = _example_fields(tmp_path, monkeypatch, scan, "mpi_lidar.CorrectionOptions(amplitude_scale=1.0)")
    truth = scan.reference_depth[las.row, las.column]
    valid = np.isfinite(las.corrected_range_m)
    assert valid.mean() > 0.9
    # the measured range unwrapped: within the noise of the truth, not a wrapped 0.6-1.3 m
    assert np.nanmedian(np.abs(las.raw_range_m[valid] - truth[valid])) < 0.02
    assert np.nanmax(np.abs(las.correction_mm[valid])) < 100.0, "a correction of millimetres, not 4.8 m"


def test_readme_python_example__scan_in_counts_gets_amplitudes_in_v2(tmp_path, monkeypatch, capsys):
    scan = render(corner(distance_m=2.0, height=16, width=24), Config(), np.random.default_rng(2))
    in_v2 = scan.amplitude[-1]
    counts = replace(scan, amplitude=(scan.amplitude * 4000.0).astype(np.float32))
    las = _example_fields(tmp_path, monkeypatch, counts, "mpi_lidar.CorrectionOptions(amplitude_scale=4000.0)")
    np.testing.assert_allclose(las.amplitude_v2, in_v2[las.row, las.column], rtol=1e-5)
    assert las.amplitude_v2.max() < 1.0


def test_point_cloud_fields__the_command_lines_writer_holds_the_same(tmp_path):
    scan = render(corner(distance_m=6.0, height=16, width=24), Config(), np.random.default_rng(6))
    model = load_model(tiny_model(tmp_path / "model", geometric=False, feature_set="raw", rounds=5,
                                  config=Config(prior=PriorConfig(d_as_m=(0.5, 8.0)))))
    correction = mpi_lidar.correct_scan(scan, model, mpi_lidar.CorrectionOptions(amplitude_scale=1.0))
    (name,) = write_point_clouds(tmp_path, (PointCloudFormat.LAZ,), scan.rays(), scan, correction)
    las = laspy.read(tmp_path / name)
    fields = mpi_lidar.point_cloud_fields(scan, correction)
    for field in ("raw_range_m", "corrected_range_m", "amplitude_v2", "flag"):
        np.testing.assert_array_equal(np.asarray(las[field]), fields[field][las.row, las.column], err_msg=field)
