"""The Python API: ``import mpi_lidar`` is light, every documented name resolves, and the README example runs."""

from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path

import laspy
import numpy as np
import pytest

import mpi_lidar
from mpi_lidar.correction import Flag
from mpi_lidar.scans.store import write_scan
from tests.model_factory import tiny_model
from tests.scan_factory import two_path_scan

pytestmark = pytest.mark.unit

README = Path(__file__).resolve().parents[1] / "README.md"
DOCUMENTED = {"load_model", "read_scan", "write_scan", "Scan", "correct_scan", "CorrectionOptions", "Config",
              "generate", "simulate_rows", "train_arrays", "train_and_save", "bayes_limit", "posterior_estimates",
              "verify_store", "write_point_cloud"}


def test_import__loads_nothing_heavy():
    # Only the lazy-import helper, which has no imports of its own.
    code = ("import sys, mpi_lidar; heavy = {'numpy', 'zarr', 'xarray', 'xgboost', 'dask', 'pydantic', 'laspy'}; "
            "print(sorted(m for m in sys.modules if m.split('.')[0] in heavy or m.startswith('mpi_lidar.')"
            " and m != 'mpi_lidar.lazy'))")
    loaded = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert loaded.strip() == "[]"


def test_api__every_exported_name_resolves():
    assert set(mpi_lidar.__all__) >= DOCUMENTED
    assert len(set(mpi_lidar.__all__)) == len(mpi_lidar.__all__)
    assert set(mpi_lidar.__all__) == {"__version__", *mpi_lidar._EXPORTS}
    for name in mpi_lidar.__all__:
        assert getattr(mpi_lidar, name) is not None, name
        assert name in dir(mpi_lidar)
    from mpi_lidar.scans.store import read_scan

    assert mpi_lidar.read_scan is read_scan
    with pytest.raises(AttributeError, match="no attribute 'nothing'"):
        _ = mpi_lidar.nothing


def readme_python_example() -> str:
    """The ```python block of the README's "Python API" section."""
    section = README.read_text().split("\n## Python API\n", 1)[1].split("\n## ", 1)[0]
    blocks = re.findall(r"```python\n(.*?)```", section, flags=re.S)
    assert len(blocks) == 1, "the Python API section holds one example"
    return blocks[0]


def test_readme_python_example__runs_and_writes_a_laz_file(tmp_path, monkeypatch, capsys):
    code = readme_python_example()
    model_dir = re.search(r'load_model\("([^"]+)"\)', code).group(1)
    scan_path = re.search(r'read_scan\("([^"]+)"\)', code).group(1)
    output = re.search(r'write_point_cloud\("([^"]+)"', code).group(1)
    tiny_model(tmp_path / model_dir, geometric=False, feature_set="raw", rounds=5)
    scan = two_path_scan(Path(scan_path).name.removesuffix(".scan.zarr"), height=12, width=16)
    scan.depth[-1, 0, 0] = np.nan  # one invalid pixel: no point
    write_scan(scan, tmp_path / scan_path)
    monkeypatch.chdir(tmp_path)
    exec(compile(code, str(README), "exec"), {})
    counts = capsys.readouterr().out
    assert "no_multipath" in counts
    las = laspy.read(tmp_path / output)
    assert las.header.are_points_compressed
    assert las.header.point_count == scan.shape[0] * scan.shape[1] - 1
    assert not ((las.row == 0) & (las.column == 0)).any()
    assert {"raw_range_m", "corrected_range_m", "correction_mm", "flag", "amplitude_v2", "uncertainty_m", "row",
            "column"} == set(las.point_format.extra_dimension_names)
    assert set(np.unique(las.flag)) <= {int(f) for f in Flag}
    raw = scan.depth[-1][las.row, las.column]
    np.testing.assert_array_equal(las.raw_range_m, raw)
    ranges = np.sqrt(np.asarray(las.x) ** 2 + np.asarray(las.y) ** 2 + np.asarray(las.z) ** 2)
    np.testing.assert_allclose(ranges, las.corrected_range_m, atol=2e-4)

