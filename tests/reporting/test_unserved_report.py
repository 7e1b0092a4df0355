"""The report of a scan the model could not serve: it draws what the scan holds, says its amplitudes' unit as known,
and its hint asks for what was not given yet."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import pytest

from mpi_lidar.correction import CorrectionOptions, ScanStatus
from mpi_lidar.correction.status import unit_hint, untrusted_unit
from mpi_lidar.scans.store import write_scan
from mpi_lidar.workflows.correct_archive import process_scan
from tests.scan_factory import two_path_scan

PROFILE_SHA = "ab" * 32


@pytest.mark.integration
@pytest.mark.parametrize("case", ["counts", "saturated everywhere"])
def test_scan_report__unserved_scan_draws_what_it_holds(case, model_dir, tmp_path):
    """In counts (the model not applied: fused depths kept) and saturated everywhere (no valid pixel): the report
    shows the maps it wrote, never says there are none, and labels the amplitudes in the scan's units."""
    scan = two_path_scan("unserved", height=8, width=12)
    options = CorrectionOptions(gate="all")
    if case == "counts":
        scan = replace(scan, amplitude=scan.amplitude * 4000)
    else:
        options = CorrectionOptions(gate="all", saturation_amplitude_v2=1e-6)
    store = write_scan(scan, tmp_path / "unserved.scan.zarr")
    outcome = process_scan(store, Path(model_dir), tmp_path / "out", options, outputs="full", point_clouds=())
    assert outcome.unserved is not None and outcome.status in (ScanStatus.UNSERVED, ScanStatus.DEGRADED), outcome
    folder = Path(outcome.output)
    report = (folder / "report.md").read_text()
    assert (folder / "maps.png").is_file() and "![maps](maps.png)" in report
    assert "no maps" not in report
    if case == "counts":
        assert "amplitude unit: not V^2" in report
    else:
        assert "show what was measured" in report and not (folder / "point_cloud.png").exists()


@pytest.mark.unit
def test_unit_hint__asks_only_for_what_was_not_given():
    neither = unit_hint(CorrectionOptions())
    assert "--sensor sensor.toml" in neither and "--amplitude-scale" in neither
    scale = unit_hint(CorrectionOptions(amplitude_scale=4000.0))
    assert "the unit given (--amplitude-scale 4000 per V^2) does not fit" in scale
    profile = unit_hint(CorrectionOptions(amplitude_scale=4000.0, sensor_profile_sha256=PROFILE_SHA))
    assert "--sensor sensor.toml" not in profile and "the sensor profile given (--sensor) does not fit" in profile
    message = untrusted_unit("too bright", CorrectionOptions(sensor_profile_sha256=PROFILE_SHA)).message
    assert message.startswith("the model was not applied: too bright; the sensor profile given")
    assert "pass --sensor" not in message and "--sensor sensor.toml" not in message
