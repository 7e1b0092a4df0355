"""A scan's speed of light and the wrap periods c / 2f it sets: recorded by the simulator, written and read by
the store (Table I's 3.0e8 for stores written before it), read or given on import, and checked against the
depths."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
import xarray as xr
import zarr

from mpi_lidar.config import Config
from mpi_lidar.constants import SPEED_OF_LIGHT_M_PER_S, TABLE_SPEED_OF_LIGHT_M_PER_S
from mpi_lidar.scans.importers import load_scan_file
from mpi_lidar.scans.scan import ScanError, validate
from mpi_lidar.scans.store import consolidate, read_scan, write_scan
from mpi_lidar.simulation.scenes import scan_from_phasors
from tests.cli_runner import assert_one_error_line, call_main
from tests.scan_factory import two_path_scan
from tests.scans.importers.files import FREQS

SCAN = two_path_scan("wrap", height=6, width=5)
PHYSICAL = SPEED_OF_LIGHT_M_PER_S


def beyond_wrap(scan=SCAN):
    """The scan with its 31.25 MHz depths unwrapped past that frequency's 4.8 m wrap period (a wall at 6.5 m)."""
    depth = np.array(scan.depth)
    depth[-1] += 4.5
    return replace(scan, depth=depth)


@pytest.mark.unit
def test_wrap_periods_m__c_over_2f_with_table_c_by_default():
    assert SCAN.speed_of_light_m_per_s == TABLE_SPEED_OF_LIGHT_M_PER_S
    assert SCAN.wrap_periods_m == pytest.approx([3e8 / (2 * f) for f in FREQS], rel=1e-15)
    assert replace(SCAN, speed_of_light_m_per_s=PHYSICAL).wrap_periods_m[-1] == pytest.approx(4.79667933, rel=1e-8)


@pytest.mark.unit
def test_content_sha256__table_c_adds_nothing_another_c_changes_it():
    assert replace(SCAN, speed_of_light_m_per_s=3.0e8).content_sha256() == SCAN.content_sha256()
    assert replace(SCAN, speed_of_light_m_per_s=PHYSICAL).content_sha256() != SCAN.content_sha256()


@pytest.mark.unit
@pytest.mark.parametrize("c", [0.0, -3e8, float("nan"), float("inf"), 3e5, 2.5e8, 3.2e8])
def test_validate__a_speed_of_light_outside_the_physical_band_is_refused(c):
    with pytest.raises(ScanError, match=r"here: speed_of_light_m_per_s is .*, not a speed of light in m/s within "
                                        r"2\.9e\+08-3\.1e\+08"):
        validate(replace(SCAN, speed_of_light_m_per_s=c), "here")


@pytest.mark.unit
def test_store__records_the_speed_of_light_and_a_store_without_it_reads_as_table_c(tmp_path):
    path = write_scan(replace(SCAN, speed_of_light_m_per_s=PHYSICAL), tmp_path / "c.scan.zarr")
    assert zarr.open_group(str(path), mode="r").attrs["speed_of_light_m_per_s"] == PHYSICAL
    assert xr.open_zarr(path).attrs["speed_of_light_m_per_s"] == PHYSICAL
    assert read_scan(path).speed_of_light_m_per_s == PHYSICAL
    group = zarr.open_group(str(path), mode="r+", use_consolidated=False)
    del group.attrs["speed_of_light_m_per_s"]  # as every store written before it
    consolidate(path)
    assert read_scan(path).speed_of_light_m_per_s == TABLE_SPEED_OF_LIGHT_M_PER_S


@pytest.mark.unit
def test_store__an_altered_speed_of_light_is_refused(tmp_path):
    path = write_scan(SCAN, tmp_path / "c.scan.zarr")
    zarr.open_group(str(path), mode="r+", use_consolidated=False).attrs["speed_of_light_m_per_s"] = "fast"
    with pytest.raises(ScanError, match=r"c\.scan\.zarr: speed_of_light_m_per_s is 'fast', not a speed of light"):
        read_scan(path)


@pytest.mark.unit
def test_store__a_wrapped_depth_beyond_its_wrap_period_is_refused_on_write_and_read(tmp_path):
    with pytest.raises(ScanError, match=r"its depth at 31\.25 MHz reaches 6\.\d+ m, beyond that frequency's wrap "
                                        r"period 4\.8000 m .*--speed-of-light M_PER_S.*--depths unwrapped"):
        write_scan(beyond_wrap(), tmp_path / "w.scan.zarr")
    assert not (tmp_path / "w.scan.zarr").exists()
    path = write_scan(replace(beyond_wrap(), depth_wrapped=False), tmp_path / "u.scan.zarr")  # unwrapped: fine
    zarr.open_group(str(path), mode="r+", use_consolidated=False).attrs["depth_wrapped"] = True
    for kept_in_store in (float("inf"), 0):  # in memory, and a band of rows at a time from the store
        with pytest.raises(ScanError, match=r"u\.scan\.zarr: its depth at 31\.25 MHz reaches 6\.\d+ m, beyond"):
            read_scan(path, stored_above_bytes=kept_in_store)


@pytest.mark.unit
def test_store__a_depth_at_its_wrap_period_within_tolerance_is_kept(tmp_path):
    depth = np.array(SCAN.depth)
    depth[-1, 0, 0] = SCAN.wrap_periods_m[-1] * (1 + 5e-4)  # a phase of 2 pi, float rounding
    assert read_scan(write_scan(replace(SCAN, depth=depth), tmp_path / "t.scan.zarr")).depth[-1, 0, 0] > 4.8


@pytest.mark.unit
def test_scan_from_phasors__records_the_simulators_speed_of_light():
    config = Config().replace(sensor={"speed_of_light_m_per_s": PHYSICAL})
    phasor = np.full((len(config.frequencies_hz), 2, 3), 0.1 + 0.05j)
    scan = scan_from_phasors("p", phasor, config, np.random.default_rng(0))
    assert scan.speed_of_light_m_per_s == PHYSICAL
    assert scan_from_phasors("p", phasor, Config(), np.random.default_rng(0)).speed_of_light_m_per_s == 3.0e8


def save(path, scan=SCAN, **extra):
    np.savez(path, depth=scan.depth, amplitude=scan.amplitude, frequencies_hz=np.asarray(FREQS), **extra)
    return path


@pytest.mark.unit
def test_load_npz__physical_c_by_default_or_the_files_own(tmp_path):
    assert load_scan_file(save(tmp_path / "a.npz")).speed_of_light_m_per_s == PHYSICAL
    own = load_scan_file(save(tmp_path / "b.npz", speed_of_light_m_per_s=np.float64(2.9979e8)))
    assert own.speed_of_light_m_per_s == 2.9979e8
    periods = 3.0e8 / (2 * np.asarray(FREQS))
    assert load_scan_file(save(tmp_path / "c.npz", wrap_period_m=periods)).speed_of_light_m_per_s == pytest.approx(
        3.0e8, rel=1e-12)
    assert load_scan_file(save(tmp_path / "d.npz"), speed_of_light_m_per_s=3.0e8).speed_of_light_m_per_s == 3.0e8


@pytest.mark.unit
@pytest.mark.parametrize(("extra", "given", "message"), [
    ({"wrap_period_m": 3.0e8 / (2 * np.asarray(FREQS)) * np.array([1, 1, 1, 1.001])}, None,
     r"wrap_period_m gives other speeds of light \(2 f L\) at its frequencies"),
    ({"wrap_period_m": np.ones(3)}, None, r"wrap_period_m must hold one period in m per frequency \(4\)"),
    ({"speed_of_light_m_per_s": np.float64(3.0e8)}, PHYSICAL,
     r"its speed_of_light_m_per_s gives c = 300000000 m/s but --speed-of-light 299792458 m/s"),
    ({"speed_of_light_m_per_s": np.float64(3.0e5)}, None, r"speed_of_light_m_per_s is 300000\.0, not a speed"),
])
def test_load_npz__inconsistent_wrap_periods_are_refused(tmp_path, extra, given, message):
    with pytest.raises(ScanError, match=message):
        load_scan_file(save(tmp_path / "a.npz", **extra), speed_of_light_m_per_s=given)


@pytest.mark.unit
def test_load_netcdf__speed_of_light_from_an_attribute_or_periods_in_mm(tmp_path):
    dims = ("frequency", "y", "x")
    maps = {"depth": (dims, SCAN.depth), "amplitude": (dims, SCAN.amplitude)}
    xr.Dataset(maps, attrs={"frequencies_hz": list(FREQS), "speed_of_light_m_per_s": 2.998e8}).to_netcdf(
        tmp_path / "a.nc", engine="h5netcdf")
    assert load_scan_file(tmp_path / "a.nc").speed_of_light_m_per_s == 2.998e8
    periods = (("frequency",), 1e3 * PHYSICAL / (2 * np.asarray(FREQS)), {"units": "mm"})
    xr.Dataset({**maps, "wrap_period_m": periods}, attrs={"frequencies_hz": list(FREQS)}).to_netcdf(
        tmp_path / "b.nc", engine="h5netcdf")
    assert load_scan_file(tmp_path / "b.nc").speed_of_light_m_per_s == pytest.approx(PHYSICAL, rel=1e-12)


@pytest.mark.integration
def test_import_scan_cli__speed_of_light_option_and_depths_beyond_their_wrap(tmp_path, monkeypatch, capsys):
    save(tmp_path / "a.npz")
    code, out, stderr = call_main(monkeypatch, capsys, "import-scan", tmp_path / "a.npz", "--out",
                                  tmp_path / "a.scan.zarr", "--speed-of-light", "3e8")
    assert code == 0, stderr
    assert "(c = 300000000 m/s)" in out and read_scan(tmp_path / "a.scan.zarr").speed_of_light_m_per_s == 3.0e8
    save(tmp_path / "far.npz", beyond_wrap())
    code, _, stderr = call_main(monkeypatch, capsys, "import-scan", tmp_path / "a.npz", tmp_path / "far.npz",
                                "--out", tmp_path / "out")
    assert code == 2 and "far.npz: its depth at 31.25 MHz reaches" in stderr and "wrap period 4.7967 m" in stderr
    assert "--depths unwrapped" in stderr
    assert_one_error_line(stderr)
    assert not (tmp_path / "out").exists()
    code, _, stderr = call_main(monkeypatch, capsys, "import-scan", tmp_path / "far.npz", "--out", tmp_path / "out",
                                "--depths", "unwrapped")
    assert code == 0, stderr
    code, _, stderr = call_main(monkeypatch, capsys, "import-scan", tmp_path / "a.npz", "--out", tmp_path / "b",
                                "--speed-of-light", "3e5")
    assert code == 2 and "--speed-of-light: speed_of_light_m_per_s is 300000.0" in stderr
