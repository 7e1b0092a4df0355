from __future__ import annotations

import json
from pathlib import Path

import pytest
import zarr

from flows.correct import SUMMARY_ARTIFACT_KEY, TABLE_ARTIFACT_KEY, correct_archive_flow
from mpi_lidar.correction import CorrectionOptions
from mpi_lidar.scans.store import write_scan
from tests.flows.helpers import artifacts
from tests.scan_factory import two_path_scan


def row(markdown: str, scan: str) -> str:
    """The batch table's row of one scan (whatever the order of its columns)."""
    [found] = [line for line in markdown.splitlines() if line.startswith(f"| {scan} |")]
    return found


@pytest.fixture(scope="module")
def archive(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("archive")
    for index, name in enumerate(("north", "south")):
        write_scan(two_path_scan(name, seed=index), root / f"{name}.scan.zarr")
    broken = root / "broken.scan.zarr"
    broken.mkdir()
    (broken / "zarr.json").write_text("{not json")
    return root


@pytest.mark.slow
def test_correct_archive_flow__bad_scan_fails_alone_and_rerun_skips(archive, small_model, tmp_path, dask_scheduler):
    out = tmp_path / "corrected"
    state = correct_archive_flow(scans=[str(archive)], model=str(small_model), out=str(out),
                                 scheduler=dask_scheduler, return_state=True)
    assert state.is_failed()
    assert "1 of 3 scans failed" in str(state.message) and "broken.scan.zarr" in str(state.message)
    assert (out / "north" / "report.html").exists() and (out / "south" / "thumbnail.png").exists()  # outputs light
    assert not (out / "broken").exists()
    summary = (out / "summary" / "report.md").read_text()
    assert "| unchanged |" in row(summary, "north") and "| ⚠ failed |" in row(summary, "broken.scan.zarr")
    assert f"- north: `{archive / 'north.scan.zarr'}`" in summary, "each scan's source is listed"
    [published] = artifacts(str(state.state_details.flow_run_id), SUMMARY_ARTIFACT_KEY)
    assert "| unchanged |" in row(published.data, "south")
    [table] = artifacts(str(state.state_details.flow_run_id), TABLE_ARTIFACT_KEY)
    rows = json.loads(table.data) if isinstance(table.data, str) else table.data
    assert sorted((row["scan"], row["status"]) for row in rows) == [
        ("broken.scan.zarr", "failed"), ("north", "unchanged"), ("south", "unchanged")]

    again = correct_archive_flow(scans=[str(archive / "north.scan.zarr"), str(archive / "south.scan.zarr")],
                                 model=str(small_model), out=str(out), scheduler=dask_scheduler)
    assert set(again["statuses"].values()) == {"skipped"}


def test_correct_archive_flow__takes_the_cli_options_and_removes_interrupted_staging(archive, small_model, tmp_path):
    """The options of `mpi-lidar correct` reach the scans, converted once; a killed run's staging goes first."""
    out = tmp_path / "corrected"
    leftover = out / ".north.writing-0123abcd"
    (leftover / "corrected.zarr").mkdir(parents=True)
    source = str(archive / "north.scan.zarr")
    result = correct_archive_flow(scans=[source], model=str(small_model), out=str(out), gate="all",
                                  min_bias_mm=1.5, footprint_area_m2=0.02, workers=0)
    assert result["statuses"] == {source: "corrected"}
    assert not leftover.exists()
    options = zarr.open_group(str(out / "north" / "corrected.zarr"), mode="r").attrs["options"]
    expected = CorrectionOptions.from_cli(gate="all", min_bias_mm=1.5, footprint_area_m2=0.02)
    assert options == expected.model_dump()
    assert expected.min_multipath_bias_m == pytest.approx(0.0015) and expected.footprint_area_m2 == 0.02


def test_correct_archive_flow__fail_on_ends_failed_after_the_summary(archive, small_model, tmp_path):
    """A status named in fail_on ends the flow Failed, after every scan and the summary were written."""
    out = tmp_path / "corrected"
    scans = [str(archive / "north.scan.zarr"), str(archive / "south.scan.zarr")]
    plain = correct_archive_flow(scans=scans, model=str(small_model), out=str(out), workers=0)
    assert set(plain["statuses"].values()) == {"unchanged"}, "without fail_on an unchanged scan is fine"
    state = correct_archive_flow(scans=scans, model=str(small_model), out=str(out), fail_on=["unchanged"],
                                 workers=0, return_state=True)
    assert state.is_failed()
    assert "2 of 2 scans unchanged" in str(state.message) and "north.scan.zarr: unchanged" in str(state.message)
    assert "0 corrected, 0 unchanged, 0 degraded, 0 unserved, 2 already done, 0 failed." in (
        out / "summary" / "report.md").read_text()
    with pytest.raises(Exception, match="fail_on"):
        correct_archive_flow(scans=scans, model=str(small_model), out=str(out), fail_on=["corrected"], workers=0)

