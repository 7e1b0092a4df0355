"""A folder name that is not UTF-8 (a byte Python keeps as a lone surrogate) reaches the sensor profile as
``\\xff``, so ``correct --sensor`` reads back what ``calibrate`` wrote."""

from __future__ import annotations

import os
import tomllib

import pytest

from mpi_lidar.calibration.profile import SensorProfile, profile_options, read_profile, write_profile
from mpi_lidar.scans.store import write_scan
from mpi_lidar.simulation.scenes import corner
from mpi_lidar.workflows.calibrate import calibrate_scans, printable_path
from tests.correction.footprint.test_estimate import rendered

pytestmark = pytest.mark.unit


@pytest.mark.parametrize(("raw", "text"), [(b"/data/caf\xff/a.scan.zarr", "/data/caf\\xff/a.scan.zarr"),
                                           ("/data/café/😀".encode(), "/data/café/😀"),
                                           (b"/plain/path", "/plain/path")])
def test_printable_path__bytes_that_are_not_utf8_become_escapes(raw, text):
    assert printable_path(os.fsdecode(raw)) == text
    text.encode("utf-8")  # never a lone surrogate


def test_write_profile__any_string_reads_back(tmp_path):
    odd = "caf\udcff \"q\" \\ \x7f\x00 é 😀"
    profile = SensorProfile.model_validate({"footprint_area_m2": 0.02, "calibration": {"sources": [odd]}})
    write_profile(profile, tmp_path / "sensor.toml")
    back = read_profile(tmp_path / "sensor.toml")
    assert back.calibration is not None
    assert back.calibration["sources"] == ["caf\\xff \"q\" \\ \x7f\x00 é 😀"]
    tomllib.loads((tmp_path / "sensor.toml").read_text(encoding="utf-8"))


def test_calibrate__folder_name_not_utf8_writes_a_profile_that_reads_back(tmp_path):
    folder = tmp_path / os.fsdecode(b"scans-caf\xff")
    for seed in (1, 2):
        write_scan(rendered(corner(90.0, 2.0, 0.8), 0.02, seed=seed), folder / f"c{seed}.scan.zarr")
    out = tmp_path / "sensor.toml"
    profile, _ = calibrate_scans([str(folder)], out)
    text = out.read_bytes().decode("utf-8")  # strict: no surrogate was written
    assert "\\udcff" not in text and "scans-caf\\\\xff" in text
    back = read_profile(out)
    assert back.footprint_area_m2 == profile.footprint_area_m2
    assert back.calibration is not None and all("scans-caf\\xff" in s for s in back.calibration["sources"])
    assert profile_options(out)["sensor_profile"]["footprint_area_m2"] == profile.footprint_area_m2
