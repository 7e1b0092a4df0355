"""Every variable of an imported file is mapped, picked up by its name, left out on request or refused
(mpi_lidar.scans.importers.base.select_variables), in NetCDF and .npz alike; angles and frequencies are
checked for their units."""

from __future__ import annotations

import numpy as np
import pytest
import xarray as xr

from mpi_lidar.scans.importers import load_scan_file
from mpi_lidar.scans.importers.base import select_variables
from mpi_lidar.scans.scan import ScanError
from mpi_lidar.scans.store import read_scan
from tests.cli_runner import assert_one_error_line, call_main
from tests.scan_factory import two_path_scan
from tests.scans.importers.files import FREQS

SCAN = two_path_scan("geo", height=6, width=5)
DIMS = ("frequency", "row", "col")


def scanner_file(path, **extra):
    """A NetCDF file as a scanner's tool writes it: its own names for the maps, geometry under plain names."""
    variables = {"range_m": (DIMS, SCAN.depth), "intensity": (DIMS, SCAN.amplitude),
                 "azimuth": (("col",), SCAN.azimuth_rad), "elevation": (("row",), SCAN.elevation_rad),
                 "frequencies_hz": (("frequency",), np.asarray(FREQS)), **extra}
    xr.Dataset(variables).to_netcdf(path, engine="h5netcdf")
    return path


MAPS = {"depth": "range_m", "amplitude": "intensity"}


@pytest.mark.unit
def test_load_netcdf__geometry_under_plain_names_is_kept(tmp_path):
    scan = load_scan_file(scanner_file(tmp_path / "scan.nc"), variables=MAPS)
    assert scan.has_geometry
    np.testing.assert_array_equal(scan.azimuth_rad, SCAN.azimuth_rad)
    np.testing.assert_array_equal(scan.elevation_rad, SCAN.elevation_rad)
    np.testing.assert_allclose(scan.rays(), SCAN.rays(), rtol=0, atol=1e-12)


@pytest.mark.unit
def test_load_netcdf__angles_in_degrees_by_name_or_units(tmp_path):
    degrees = {"az_deg": (("col",), np.degrees(SCAN.azimuth_rad)), "el": (("row",), np.degrees(SCAN.elevation_rad),
                                                                          {"units": "degrees"})}
    path = scanner_file(tmp_path / "deg.nc", **degrees)
    scan = load_scan_file(path, variables={**MAPS, "azimuth_deg": "az_deg", "elevation": "el",
                                           "ignore": "azimuth,elevation"})
    np.testing.assert_allclose(scan.azimuth_rad, SCAN.azimuth_rad, rtol=1e-12)
    np.testing.assert_allclose(scan.elevation_rad, SCAN.elevation_rad, rtol=1e-12)


@pytest.mark.unit
def test_load_netcdf__degrees_read_as_radians_are_refused(tmp_path):
    path = scanner_file(tmp_path / "deg.nc", az_deg=(("col",), np.linspace(-30, 30, 5)))
    with pytest.raises(ScanError, match=r"azimuth_rad reaches 30, .* in degrees; import it with --var "
                                        r"azimuth_deg=VARIABLE") as error:
        load_scan_file(path, variables={**MAPS, "azimuth": "az_deg", "ignore": "azimuth"})
    assert "\n" not in str(error.value)


@pytest.mark.unit
def test_load_netcdf__an_unknown_variable_is_refused_naming_the_var_that_maps_it(tmp_path):
    path = scanner_file(tmp_path / "extra.nc", temperature=(("row", "col"), np.zeros((6, 5))))
    with pytest.raises(ScanError, match=r"variable 'temperature' is not a scan array and would be dropped; map it "
                                        r"with --var NAME=temperature .* --var ignore=temperature"):
        load_scan_file(path, variables=MAPS)
    assert load_scan_file(path, variables={**MAPS, "ignore": "temperature"}).has_geometry


@pytest.mark.unit
def test_load_netcdf__dimension_coordinates_and_scalars_are_metadata(tmp_path):
    path = scanner_file(tmp_path / "meta.nc", timestamp=((), 1.7e9), col=(("col",), np.arange(5)))
    assert load_scan_file(path, variables=MAPS).shape == (6, 5)


@pytest.mark.unit
def test_load_netcdf__frequencies_in_mhz_are_refused_unless_declared(tmp_path):
    path = scanner_file(tmp_path / "mhz.nc", frequencies_hz=(("frequency",), np.asarray(FREQS) / 1e6))
    with pytest.raises(ScanError, match=r"below 10000 Hz; frequencies are in Hz \(12.5 MHz is 1.25e\+07\)"):
        load_scan_file(path, variables=MAPS)
    attribute = tmp_path / "attribute.nc"
    xr.Dataset({"depth": (DIMS, SCAN.depth), "amplitude": (DIMS, SCAN.amplitude)},
               attrs={"frequencies_hz": np.asarray(FREQS) / 1e6}).to_netcdf(attribute, engine="h5netcdf")
    with pytest.raises(ScanError, match=r"attribute\.nc: frequency 12.5 Hz is below 10000 Hz"):
        load_scan_file(attribute)
    declared = scanner_file(tmp_path / "declared.nc",
                            frequencies_hz=(("frequency",), np.asarray(FREQS) / 1e6, {"units": "MHz"}))
    assert load_scan_file(declared, variables=MAPS).frequencies_hz == pytest.approx(FREQS, rel=1e-12)


@pytest.mark.unit
@pytest.mark.parametrize(("extra", "variables", "message"), [
    ({"azimuth_rad": (("col",), SCAN.azimuth_rad)}, MAPS, "holds both 'azimuth' and 'azimuth_rad' for azimuth_rad"),
    ({"depth": (DIMS, SCAN.depth)}, MAPS, r"holds \['depth'\] itself and --var maps other arrays to them"),
    ({"az_deg": (("col",), SCAN.azimuth_rad, {"units": "rad"})}, {**MAPS, "azimuth_deg": "az_deg", "ignore": "azimuth"},
     "mapped as degrees but its variable has units 'rad'"),
    ({}, {**MAPS, "azimuth": "range_m"}, "map each variable once"),
    ({}, {**MAPS, "azimuth_deg": "azimuth", "azimuth_rad": "elevation"}, "maps azimuth_rad twice"),
    ({}, {**MAPS, "ignore": "humidity"}, "no variable for --var ignore=humidity"),
])
def test_load_netcdf__conflicting_names_are_one_clear_error(tmp_path, extra, variables, message):
    path = scanner_file(tmp_path / "bad.nc", **extra)
    with pytest.raises(ScanError, match=message) as error:
        load_scan_file(path, variables=variables)
    assert "\n" not in str(error.value)


@pytest.mark.unit
def test_load_npz__same_names_and_refusals_as_netcdf(tmp_path):
    np.savez(tmp_path / "plain.npz", range_m=SCAN.depth, intensity=SCAN.amplitude, frequencies_hz=FREQS,
             azimuth_deg=np.degrees(SCAN.azimuth_rad), elevation=SCAN.elevation_rad, colour=SCAN.reference_depth)
    with pytest.raises(ScanError, match=r"variable 'colour' is not a scan array .* --var ignore=colour"):
        load_scan_file(tmp_path / "plain.npz", variables=MAPS)
    scan = load_scan_file(tmp_path / "plain.npz", variables={**MAPS, "reference_depth": "colour"})
    np.testing.assert_allclose(scan.azimuth_rad, SCAN.azimuth_rad, rtol=1e-12)
    np.testing.assert_array_equal(scan.elevation_rad, SCAN.elevation_rad)
    np.testing.assert_array_equal(scan.reference_depth, SCAN.reference_depth)


@pytest.mark.unit
@pytest.mark.parametrize(("arrays", "message"), [
    ({"elevation_rad": np.linspace(-10, 10, 6)}, "elevation_rad reaches 10, .* --var elevation_deg=VARIABLE"),
    ({"azimuth_rad": np.array([0, 0.1, np.nan, 0.3, 0.4])}, "azimuth_rad has values that are not finite"),
    ({"ray_directions": 2 * SCAN.rays()}, "ray_directions are not unit vectors"),
])
def test_load_npz__implausible_geometry_is_refused(tmp_path, arrays, message):
    np.savez(tmp_path / "geo.npz", depth=SCAN.depth, amplitude=SCAN.amplitude, frequencies_hz=FREQS, **arrays)
    with pytest.raises(ScanError, match=message):
        load_scan_file(tmp_path / "geo.npz")


@pytest.mark.unit
def test_select_variables__every_variable_accounted_for():
    held = ["range_m", "intensity", "azimuth", "elevation_deg", "x", "notes"]
    chosen = select_variables("f", held, {**MAPS, "ignore": "notes"}, metadata=["x"])
    assert {name: (s.variable, s.degrees) for name, s in chosen.items()} == {
        "depth": ("range_m", False), "amplitude": ("intensity", False), "azimuth_rad": ("azimuth", False),
        "elevation_rad": ("elevation_deg", True)}


@pytest.mark.integration
def test_import_scan_cli__netcdf_geometry_is_kept_or_refused(tmp_path, monkeypatch, capsys):
    path = scanner_file(tmp_path / "scan.nc")
    code, out, err = call_main(monkeypatch, capsys, "import-scan", path, "--out", tmp_path / "scan.scan.zarr",
                               "--var", "depth=range_m", "--var", "amplitude=intensity")
    assert code == 0, err
    assert read_scan(tmp_path / "scan.scan.zarr").has_geometry
    extra = scanner_file(tmp_path / "extra.nc", quality=(DIMS, SCAN.amplitude))
    code, out, err = call_main(monkeypatch, capsys, "import-scan", extra, "--out", tmp_path / "extra.scan.zarr",
                               "--var", "depth=range_m", "--var", "amplitude=intensity")
    assert code == 2 and out == ""
    assert_one_error_line(err, "variable 'quality' is not a scan array")
    assert not (tmp_path / "extra.scan.zarr").exists()
