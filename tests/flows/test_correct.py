from __future__ import annotations

from pathlib import Path

import pytest
import zarr

from flows.correct import SUMMARY_ARTIFACT_KEY, correct_archive_flow
from mpi_lidar.correction import CorrectionOptions
from mpi_lidar.scans.scan import write_scan
from tests.flows.helpers import artifacts
from tests.scan_factory import two_path_scan


@pytest.fixture(scope="module")
def archive(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("archive")
    for index, name in enumerate(("north", "south")):
        write_scan(two_path_scan(name, seed=index), root / f"{name}.scan.zarr")
    broken = root / "broken.scan.zarr"
    broken.mkdir()
    (broken / "zarr.json").write_text("{not json")
    return root


def test_correct_archive_flow__bad_scan_fails_alone_and_rerun_skips(archive, small_model, tmp_path, dask_scheduler):
    out = tmp_path / "corrected"
    state = correct_archive_flow(scans=[str(archive)], model=str(small_model), out=str(out),
                                 scheduler=dask_scheduler, return_state=True)
    assert state.is_failed()
    assert "1 of 3 scans failed" in str(state.message) and "broken.scan.zarr" in str(state.message)
    assert (out / "north" / "report.html").exists() and (out / "south" / "maps.png").exists()
    assert not (out / "broken").exists()
    summary = (out / "summary" / "report.md").read_text()
    assert "| north | corrected |" in summary and "| broken.scan.zarr | failed |" in summary
    [published] = artifacts(str(state.state_details.flow_run_id), SUMMARY_ARTIFACT_KEY)
    assert "| south | corrected |" in published.data

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
