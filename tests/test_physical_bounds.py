"""Physical quantities of sensor profiles and correction options: strict numbers within documented bounds.

A boolean is no number of square metres, and a footprint of 1e9 m^2 no footprint: each is refused with one
line naming the field and its bound (docs/reference/configuration.md, "Physical bounds")."""

from __future__ import annotations

import math
import re
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import zarr
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from mpi_lidar.calibration.profile import FREQUENCY_BOUNDS_HZ, MAX_OFFSET_M, check_profile_frequencies, read_profile
from mpi_lidar.correction.options import (
    AMPLITUDE_SCALE_BOUNDS,
    MAX_AMPLITUDE_V2,
    MAX_BIAS_M,
    MAX_BLOCK_M,
    MAX_DEPTH_M,
    MAX_FOOTPRINT_AREA_M2,
    MAX_SIGMAS,
    NO_SATURATION_V2,
    NOISE_SCALE_BOUNDS,
    CorrectionOptions,
    Flag,
    ScanStatus,
    UnservedReason,
)
from mpi_lidar.correction.outcome import Unserved, degraded_reason, first_cause, scan_status, status_reason
from mpi_lidar.errors import MpiLidarError
from mpi_lidar.scans.scan import ScanError, validate
from mpi_lidar.scans.store import read_scan, store_fingerprints, write_scan
from tests.cli_runner import assert_one_error_line, call_main
from tests.model_factory import tiny_model
from tests.scan_factory import two_path_scan

# field: (lowest allowed, highest allowed, whether the lowest itself is allowed), of CorrectionOptions.
OPTION_BOUNDS = {
    "footprint_area_m2": (0.0, MAX_FOOTPRINT_AREA_M2, False),
    "amplitude_scale": (*AMPLITUDE_SCALE_BOUNDS, True),
    "saturation_amplitude_v2": (0.0, NO_SATURATION_V2, False),  # a profile: MAX_AMPLITUDE_V2
    "min_amplitude_sigmas": (0.0, MAX_SIGMAS, True),
    "max_depth_spread_m": (0.0, MAX_DEPTH_M, False),
    "range_tolerance_m": (0.0, MAX_DEPTH_M, True),
    "min_multipath_bias_m": (0.0, MAX_BIAS_M, True),
    "geometry_block_m": (0.0, MAX_BLOCK_M, False),
    "partner_range_m": (0.0, MAX_DEPTH_M, False),
    "near_range_fraction": (0.0, 1.0, True),
    "consistency_p_value": (0.0, 1.0, False),
    "max_invalid_share": (0.0, 1.0, True),
}
PROFILE_BOUNDS = {**{name: OPTION_BOUNDS[name] for name in ("footprint_area_m2", "amplitude_scale",
                                                            "min_amplitude_sigmas")},
                  "saturation_amplitude_v2": (0.0, MAX_AMPLITUDE_V2, False)}
PROFILE = 'schema = "mpi-lidar/sensor@1"\nfootprint_area_m2 = 0.0231\n'
bounds_settings = settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])


def inside(low: float, high: float, low_allowed: bool, value: float) -> bool:
    return (low < value or (low_allowed and value == low)) and value <= high


def toml_number(value: float) -> str:
    return "nan" if math.isnan(value) else ("inf" if value > 0 else "-inf") if math.isinf(value) else repr(value)


@pytest.mark.unit
@given(name=st.sampled_from(sorted(OPTION_BOUNDS)), value=st.floats(allow_nan=True, allow_infinity=True))
@bounds_settings
def test_correction_options__a_value_is_accepted_exactly_within_its_bounds(name, value):
    low, high, low_allowed = OPTION_BOUNDS[name]
    if name == "near_range_fraction":
        high = math.nextafter(1.0, 0)  # [0, 1)
    if name == "consistency_p_value":
        high = math.nextafter(1.0, 0)  # (0, 1)
    try:
        options = CorrectionOptions(**{name: value})
    except ValueError:
        assert not inside(low, high, low_allowed, value)
    else:
        assert inside(low, high, low_allowed, value) and getattr(options, name) == value


@pytest.mark.unit
@pytest.mark.parametrize("name", [*sorted(OPTION_BOUNDS), "tile_pixels"])
@pytest.mark.parametrize("value", [True, False, "1", "0.5"])
def test_correction_options__booleans_and_strings_are_no_numbers(name, value):
    with pytest.raises(ValueError):
        CorrectionOptions(**{name: value})


@pytest.mark.integration
@pytest.mark.parametrize("given_value", ["1e9", "1e308", 1e9, 1e308, True, "-0.1", "nan", "inf", 0])
def test_from_cli__footprint_past_its_physical_bound_is_one_line(given_value):
    with pytest.raises(MpiLidarError) as refused:
        CorrectionOptions.from_cli(footprint_area_m2=given_value)
    assert "(0, 1]" in str(refused.value) and "\n" not in str(refused.value)


@pytest.mark.integration
@pytest.mark.parametrize("given_value", ["1e-30", 1e12, False, "-4000"])
def test_from_cli__amplitude_scale_past_its_physical_bound_is_one_line(given_value):
    with pytest.raises(MpiLidarError, match=r"\[1e-06, 1e\+09\]"):
        CorrectionOptions.from_cli(amplitude_scale=given_value)


@pytest.mark.integration
def test_from_cli__values_within_bounds_and_auto():
    options = CorrectionOptions.from_cli(footprint_area_m2="1.0", amplitude_scale="4000", min_bias_mm=2.5)
    assert (options.footprint_area_m2, options.amplitude_scale, options.min_multipath_bias_m) == (1.0, 4000.0, 0.0025)
    assert CorrectionOptions.from_cli(footprint_area_m2="auto", amplitude_scale="AUTO").amplitude_scale == "auto"


@pytest.mark.unit
@given(name=st.sampled_from(sorted(PROFILE_BOUNDS)),
       value=st.one_of(st.floats(allow_nan=True, allow_infinity=True), st.booleans(),
                       st.integers(min_value=-10, max_value=10**12)))
@bounds_settings
def test_read_profile__each_number_strict_and_within_its_bounds(tmp_path, name, value):
    path = tmp_path / "sensor.toml"
    written = ("true" if value else "false") if isinstance(value, bool) else (
        str(value) if isinstance(value, int) else toml_number(value))
    lines = [line for line in PROFILE.splitlines() if not line.startswith(f"{name} =")]
    path.write_text("\n".join([*lines, f"{name} = {written}"]) + "\n")
    low, high, low_allowed = PROFILE_BOUNDS[name]
    try:
        profile = read_profile(path)
    except MpiLidarError as exc:
        assert isinstance(value, bool) or not inside(low, high, low_allowed, value)
        assert name in str(exc) and "\n" not in str(exc)
    else:
        assert not isinstance(value, bool) and inside(low, high, low_allowed, value)
        assert getattr(profile, name) == value


@pytest.mark.unit
@pytest.mark.parametrize(("line", "fragment"), [
    ("footprint_area_m2 = true", "footprint_area_m2"),
    ("frequencies_hz = [12.5e6, true]", "frequencies_hz"),
    (f"frequencies_hz = [{FREQUENCY_BOUNDS_HZ[1] * 10:g}]", "frequencies_hz"),
    ("frequencies_hz = [0.5]", "frequencies_hz"),
    ("frequencies_hz = []", "frequencies_hz"),
    ("frequencies_hz = [12.5e6, 12.5e6]", "duplicates"),
    ("noise_scale = 1e9", "noise_scale"),
    ("noise_scale = false", "noise_scale"),
    ("range_m = [7.5, 0.6]", "near < far"),
    (f"range_m = [0.6, {MAX_DEPTH_M * 10:g}]", "range_m"),
    ("range_m = [0.0, 7.5]", "range_m"),
    (f"frequency_offsets_m = [{MAX_OFFSET_M * 2:g}]", "frequency_offsets_m"),
    ('frequency_offsets_m = ["0.001"]', "frequency_offsets_m"),
    ("frequencies_hz = [12.5e6, 25e6]\nfrequency_offsets_m = [0.001]", "one per frequency"),
])
def test_read_profile__nonsense_refused(tmp_path, line, fragment):
    path = tmp_path / "sensor.toml"
    path.write_text(PROFILE.replace("footprint_area_m2 = 0.0231\n", "") + line + "\n"
                    + ("" if line.startswith("footprint") else "footprint_area_m2 = 0.0231\n"))
    with pytest.raises(MpiLidarError, match=fragment):
        read_profile(path)


@pytest.mark.unit
def test_read_profile__a_calibrated_profile_reads_back(tmp_path):
    path = tmp_path / "sensor.toml"
    path.write_text(PROFILE + "frequencies_hz = [12500000.0, 31250000.0]\nnoise_scale = 1.02\nrange_m = [0.6, 7.5]\n"
                    "frequency_offsets_m = [-0.00058, 0.0]\namplitude_scale = 4000\n")
    profile = read_profile(path)
    assert profile.range_m == (0.6, 7.5) and profile.amplitude_scale == 4000.0


@pytest.mark.unit
@pytest.mark.parametrize("args", [("--footprint-area-m2", "1e9"), ("--footprint-area-m2", "1e308"),
                                  ("--amplitude-scale", "1e-30")])
def test_correct__option_past_its_bound_is_one_line_and_writes_nothing(tmp_path, monkeypatch, capsys, args):
    out = tmp_path / "corrected"
    code, _, stderr = call_main(monkeypatch, capsys, "correct", tmp_path / "a.scan.zarr", "--model", tmp_path / "m",
                                "--out", out, *args)
    assert code == 2
    assert_one_error_line(stderr, "physical bounds")
    assert not out.exists()


@pytest.mark.unit
def test_correct__profile_with_a_boolean_footprint_is_one_line(tmp_path: Path, monkeypatch, capsys):
    sensor = tmp_path / "sensor.toml"
    sensor.write_text(PROFILE.replace("0.0231", "true"))
    code, _, stderr = call_main(monkeypatch, capsys, "correct", tmp_path / "a.scan.zarr", "--model", tmp_path / "m",
                                "--out", tmp_path / "corrected", "--sensor", sensor)
    assert code == 2
    assert_one_error_line(stderr, "footprint_area_m2")
    assert not (tmp_path / "corrected").exists()


# --- a scan's own values, where they are read ----------------------------------------------------------------

SCAN = two_path_scan("bounds", height=6, width=8)
AZIMUTH, ELEVATION = np.linspace(-0.2, 0.2, 8), np.linspace(-0.15, 0.15, 6)


@pytest.mark.unit
@pytest.mark.parametrize(("change", "fragment"), [
    ({"depth": np.asarray(SCAN.depth) - 13.0}, "a phase's depth is never negative"),
    ({"depth": np.asarray(SCAN.depth) - 13.0, "depth_wrapped": False}, "never by more than 1 m"),
    ({"amplitude": np.full_like(SCAN.amplitude, 1e30)}, "every finite amplitude is 1e+30"),
    ({"amplitude": np.full_like(SCAN.amplitude, 1e-12)}, "every finite amplitude is 1e-12"),
    ({"azimuth_rad": np.where(np.arange(8) == 3, np.nan, AZIMUTH)}, "azimuth_rad has values that are not"),
    ({"elevation_rad": np.where(np.arange(6) == 2, np.inf, ELEVATION)}, "elevation_rad has values that"),
    ({"elevation_rad": np.linspace(-1e5, 1e5, 6)}, "elevation_rad reaches 100000"),
])
def test_scan_store__values_past_their_physical_bounds_are_refused_where_read(tmp_path, change, fragment):
    """Written or read back (as another tool may write the store), each is one line naming what is wrong."""
    scan = replace(SCAN, **change)
    with pytest.raises(ScanError, match=re.escape(fragment)) as refused:
        write_scan(scan, tmp_path / "w.scan.zarr")
    assert "\n" not in str(refused.value)
    assert not (tmp_path / "w.scan.zarr").exists()
    path = write_scan(SCAN, tmp_path / "r.scan.zarr")
    group = zarr.open_group(str(path), mode="r+")
    for name, value in change.items():
        if name == "depth_wrapped":
            continue
        group[name][...] = value
    group.attrs["chunk_sha256"] = store_fingerprints(group)  # as a tool that writes such values records them
    if "depth_wrapped" in change:
        group.attrs["depth_wrapped"] = False
    with pytest.raises(ScanError, match=re.escape(fragment)):
        read_scan(path)


@pytest.mark.unit
def test_validate__amplitudes_all_zero_are_a_scan_without_a_return_not_refused():
    assert validate(replace(SCAN, amplitude=np.zeros_like(SCAN.amplitude)), "zero").shape == SCAN.shape


# --- one place decides a scan's status and its reason ----------------------------------------------------------


@pytest.mark.unit
@pytest.mark.parametrize("flag", ["inconsistent", "not_finite", "no_return"])
def test_scan_status__invalid_data_first_never_the_amplitude_units(flag):
    counts = {flag: 90, "uncalibrated": 10}
    status = scan_status(counts, 0.5, UnservedReason.AMPLITUDE_UNITS)
    assert status == ScanStatus.DEGRADED
    reason = status_reason(status, counts, Unserved(UnservedReason.AMPLITUDE_UNITS, "give --amplitude-scale"))
    assert reason.startswith(f"90.0 % of its pixels are invalid, first {flag} (90.0 %")
    assert "amplitude-scale" not in reason


@pytest.mark.unit
def test_scan_status__saturation_nearly_everywhere_is_the_units():
    counts = {"saturated": 95, "inconsistent": 3, "not_needed": 2}
    assert scan_status(counts, 0.5, UnservedReason.AMPLITUDE_UNITS) == ScanStatus.UNSERVED
    assert scan_status(counts, 0.5) == ScanStatus.DEGRADED
    assert first_cause(counts) == Flag.SATURATED
    assert degraded_reason(counts).endswith("then inconsistent 3.0 %")
    assert scan_status({"not_needed": 10}, 0.5) == ScanStatus.UNCHANGED and first_cause({"not_needed": 1}) is None


# --- noise scale, profile frequencies --------------------------------------------------------------------------


@pytest.mark.unit
def test_noise_scale__a_lower_bound_keeps_every_uncertainty(tmp_path):
    sensor = tmp_path / "sensor.toml"
    sensor.write_text(PROFILE + "noise_scale = 1e-300\n")
    with pytest.raises(MpiLidarError, match="noise_scale"):
        read_profile(sensor)
    with pytest.raises(MpiLidarError, match="noise_scale"):
        CorrectionOptions.from_cli(sensor_profile={"noise_scale": 1e-300})
    assert CorrectionOptions(noise_scale=NOISE_SCALE_BOUNDS[0]).noise_scale == NOISE_SCALE_BOUNDS[0]


@pytest.fixture(scope="module")
def raw_model(tmp_path_factory) -> Path:
    return tiny_model(tmp_path_factory.mktemp("model") / "model", geometric=False, feature_set="raw", rounds=5)


@pytest.mark.unit
@pytest.mark.parametrize(("lines", "fragment"), [
    ("frequency_offsets_m = [0.001, 0.0]\n", "gives 2 frequency_offsets_m for the 4 frequencies"),
    ("frequencies_hz = [1e7, 1.5e7, 2e7, 3e7]\n", "calibrated at 10, 15, 20, 30 MHz"),
])
def test_correct__profile_of_other_frequencies_is_one_line_exit_2(tmp_path, monkeypatch, capsys, raw_model,
                                                                   lines, fragment):
    sensor = tmp_path / "sensor.toml"
    sensor.write_text(PROFILE + lines)
    scan = write_scan(SCAN, tmp_path / "a.scan.zarr")
    out = tmp_path / "corrected"
    code, _, stderr = call_main(monkeypatch, capsys, "correct", scan, "--model", raw_model, "--out", out,
                                "--sensor", sensor)
    assert code == 2
    assert_one_error_line(stderr, fragment)
    assert not out.exists()
    with pytest.raises(MpiLidarError, match=fragment):
        check_profile_frequencies(read_profile(sensor), (12.5e6, 18.75e6, 25e6, 31.25e6), "the scan", sensor)
