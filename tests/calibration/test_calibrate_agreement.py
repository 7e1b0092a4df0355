"""``calibrate`` reports what each scan measured, records the scans' speed of light, and refuses scans that are
not one sensor's in one unit: amplitude units far apart, or other speeds of light."""

from __future__ import annotations

from dataclasses import replace
from functools import cache

import numpy as np
import pytest

from mpi_lidar.calibration.profile import read_profile
from mpi_lidar.calibration.sensor_scale import SensorScale
from mpi_lidar.config import Config
from mpi_lidar.constants import SPEED_OF_LIGHT_M_PER_S
from mpi_lidar.correction.footprint import NOTHING_MEASURED
from mpi_lidar.errors import MpiLidarError
from mpi_lidar.scans.scan import Scan
from mpi_lidar.scans.store import write_scan
from mpi_lidar.simulation.scenes import DEFAULT_FOOTPRINT_RADIUS_M, render, room_corner
from mpi_lidar.workflows.calibrate import ScanEstimate, check_units_agree
from tests.cli_runner import assert_one_error_line, call_main
from tests.render_cache import transport_shared_as


@cache
def room(seed: int) -> Scan:
    """A small room corner with a footprint of 0.02 m^2: walls and a floor whose flat parts measure the unit.

    The seeds share the light transport, which draws nothing (the sensor model draws the noise): the same scans,
    bit for bit, without a second transport (5 s)."""
    gain = 0.02 / (np.pi * DEFAULT_FOOTPRINT_RADIUS_M**2)
    with transport_shared_as("calibrate-agreement room"):
        return render(room_corner(height=64, width=86), Config(), np.random.default_rng(seed), coupling_gain=gain)


def measured(source: str, unit: float, sigma: float, significant: bool = True) -> ScanEstimate:
    """A scan's estimate whose flat surfaces read ``unit`` +- ``sigma`` per V^2."""
    scale = SensorScale(unit, sigma, 1.0, 0.0, np.zeros(4), np.full(4, 1e-4), 500, significant, "")
    return ScanEstimate(source, NOTHING_MEASURED, scale)


@pytest.mark.unit
@pytest.mark.parametrize(("units", "refused"), [
    ([(1.0, 0.03), (4012.0, 120.0)], True),  # V^2 and counts
    ([(1.0, 0.03), (1.05, 0.03), (2.5, 0.05)], True),  # one scan 2.5-fold from another: not one unit
    ([(1.0, 0.03), (1.9, 0.05)], False),  # within the twofold band
    ([(1.0, 0.03), (2.5, 0.6)], False),  # 2.5-fold, but not beyond twice their uncertainty
    ([(1.0, 0.03), (4000.0, 10.0, False)], False),  # a scan whose unit was not measured says nothing
])
def test_check_units_agree__units_more_than_twofold_apart_beyond_their_uncertainty(units, refused):
    results = [measured(f"s{i}.scan.zarr", *unit) for i, unit in enumerate(units)]
    if not refused:
        check_units_agree(results)
        return
    with pytest.raises(MpiLidarError, match=r"scan s0\.scan\.zarr reads 1 \+- 0\.03 per V\^2, scan s\d\.scan\.zarr "
                                            r"\d.* per V\^2: their amplitudes are in units .*-fold apart"):
        check_units_agree(results)


@pytest.mark.integration
@pytest.mark.slow
def test_calibrate__amplitude_units_4000_fold_apart_are_refused(tmp_path, monkeypatch, capsys):
    write_scan(room(1), tmp_path / "scans" / "a.scan.zarr")
    counts = replace(room(2), amplitude=(room(2).amplitude * 4000).astype(np.float32))
    write_scan(counts, tmp_path / "scans" / "b.scan.zarr")
    code, out, stderr = call_main(monkeypatch, capsys, "calibrate", str(tmp_path / "scans"), "--out",
                                  str(tmp_path / "sensor.toml"))
    assert code == 2, stderr
    assert "a.scan.zarr reads 1" in stderr and "b.scan.zarr 4" in stderr and "-fold apart" in stderr
    assert_one_error_line(stderr)
    assert not (tmp_path / "sensor.toml").exists()
    lines = out.splitlines()  # each scan's values were reported before the refusal
    assert len(lines) == 2 and all("amplitude unit" in line and "c = 300000000 m/s" in line for line in lines)


@pytest.mark.integration
@pytest.mark.slow
def test_calibrate__other_speeds_of_light_are_refused(tmp_path, monkeypatch, capsys):
    write_scan(room(1), tmp_path / "scans" / "a.scan.zarr")
    write_scan(replace(room(1), speed_of_light_m_per_s=SPEED_OF_LIGHT_M_PER_S), tmp_path / "scans" / "b.scan.zarr")
    code, _, stderr = call_main(monkeypatch, capsys, "calibrate", str(tmp_path / "scans"), "--out",
                                str(tmp_path / "sensor.toml"))
    assert code == 2
    assert "b.scan.zarr converts phase to range with c = 299792458 m/s" in stderr and "300000000 m/s" in stderr
    assert_one_error_line(stderr)
    assert not (tmp_path / "sensor.toml").exists()


@pytest.mark.integration
@pytest.mark.slow
def test_calibrate__records_the_scans_speed_of_light_and_each_scans_values(tmp_path, monkeypatch, capsys):
    for seed in (1, 2):
        write_scan(replace(room(seed), speed_of_light_m_per_s=SPEED_OF_LIGHT_M_PER_S),
                   tmp_path / "scans" / f"r{seed}.scan.zarr")
    code, out, stderr = call_main(monkeypatch, capsys, "calibrate", str(tmp_path / "scans"), "--out",
                                  str(tmp_path / "sensor.toml"))
    assert code == 0, stderr
    profile = read_profile(tmp_path / "sensor.toml")
    assert profile.speed_of_light_m_per_s == SPEED_OF_LIGHT_M_PER_S
    assert "c = 299792458 m/s; sensor profile written" in out
    assert profile.calibration is not None
    scans = profile.calibration["scans"]
    assert isinstance(scans, list) and len(scans) == 2
    for seed, line in zip((1, 2), scans, strict=True):
        assert f"r{seed}.scan.zarr: " in line and "per V^2" in line and "frequency offsets" in line
        assert line.endswith("c = 299792458 m/s") and line in out
