"""The terminal summary of a batch run into an --out that earlier batches filled: this batch's scans only."""

from __future__ import annotations

import pytest

from tests.cli_runner import call_main

pytestmark = pytest.mark.integration


def test_correct__piped_table_lists_this_batch_only_in_80_columns(monkeypatch, capsys, tmp_path):
    """A second batch into the same --out: its terminal table lists its own scan, not the earlier batch's (the
    summary's files hold those), in 80 columns with no progress line before the result."""
    from mpi_lidar.scans.store import write_scan
    from tests.model_factory import tiny_model
    from tests.scan_factory import two_path_scan

    monkeypatch.delenv("COLUMNS", raising=False)
    model = tiny_model(tmp_path / "model", rows=1_000, rounds=5)
    names = ("corridor_north_wing_2026-11-25_station_0001", "b", "c")
    for seed, name in enumerate(names):
        write_scan(two_path_scan(name, height=6, width=8, seed=seed), tmp_path / "scans" / f"{name}.scan.zarr")
    args = ["--model", model, "--out", tmp_path / "out", "--gate", "all", "--outputs", "data"]
    first = [tmp_path / "scans" / f"{name}.scan.zarr" for name in names[:2]]
    code, out, err = call_main(monkeypatch, capsys, "correct", *first, *args)
    assert code == 0, err
    assert any(line.startswith("2 scans in") for line in out.splitlines()), out
    code, out, err = call_main(monkeypatch, capsys, "correct", tmp_path / "scans" / "c.scan.zarr", *args)
    assert code == 0, err
    lines = out.splitlines()
    lines = lines[next(i for i, line in enumerate(lines) if line.endswith("s: 1 corrected")):]  # after the progress
    where = str(tmp_path / "out" / "summary" / "report.html")
    assert lines[0].startswith("1 scan in") and lines[-2:] == ["summary (every note in full):", where], out
    assert all(len(line) <= 80 for line in lines[:-1]), out  # all but the summary's path, whole on its own line
    rows = [line.split()[0] for line in lines[lines.index(next(x for x in lines if x.startswith("scan "))) + 2:]
            if line and not line.startswith(("n", "summary", "/"))]
    assert rows == ["c"], out
    assert "correcting scans: 0/" not in out  # no progress line before the first scan is done
    summary = (tmp_path / "out" / "summary" / "report.md").read_text()
    assert summary.startswith("# Batch correction\n\n3 scans in"), "the summary counts the whole folder"
