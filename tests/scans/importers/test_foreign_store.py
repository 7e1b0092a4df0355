"""A Zarr store another tool wrote, given to correct or verify: not a damaged scan but one to import first."""

from __future__ import annotations

import pytest
import xarray as xr

from mpi_lidar.scans.store import read_scan
from tests.cli_runner import assert_one_error_line, call_main
from tests.model_factory import tiny_model
from tests.scan_factory import two_path_scan


def _foreign(path, schema: str | None):
    scan = two_path_scan("x", height=6, width=5)
    dims = ("frequency", "y", "x")
    attrs = {"frequencies_hz": list(scan.frequencies_hz)} | ({} if schema is None else {"schema": schema})
    xr.Dataset({"depth": (dims, scan.depth), "amplitude": (dims, scan.amplitude)}, attrs=attrs).to_zarr(
        path, mode="w", consolidated=False)
    return path


@pytest.mark.unit
@pytest.mark.parametrize("schema", [None, "mpi-lidar/scan@1"])
def test_verify__a_foreign_zarr_store_is_to_import_not_damaged(tmp_path, monkeypatch, capsys, schema):
    store = _foreign(tmp_path / "tool.scan.zarr", schema)
    code, stdout, stderr = call_main(monkeypatch, capsys, "verify", store)
    assert code == 1 and not stdout
    assert_one_error_line(stderr, "is not a scan store")
    assert "import it first: mpi-lidar import-scan" in stderr and "damaged" not in stderr
    with pytest.raises(Exception, match="import it first") as error:
        read_scan(store)
    assert "damaged" not in str(error.value)


@pytest.mark.integration
def test_correct__a_foreign_zarr_store_fails_pointing_to_import_scan(tmp_path, monkeypatch, capsys):
    _foreign(tmp_path / "scans" / "tool.scan.zarr", "mpi-lidar/scan@1")
    model = tiny_model(tmp_path / "model")
    code, stdout, stderr = call_main(monkeypatch, capsys, "correct", tmp_path / "scans", "--model", model,
                                     "--out", tmp_path / "out", "--gate", "all")
    assert code == 1 and "1 failed" in stdout
    assert_one_error_line(stderr, "import it first: mpi-lidar import-scan")
    assert "damaged" not in stderr and "damaged" not in stdout
