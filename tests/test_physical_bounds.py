"""Physical quantities of sensor profiles and correction options: strict numbers within documented bounds.

A boolean is no number of square metres, and a footprint of 1e9 m^2 no footprint: each is refused with one
line naming the field and its bound (docs/reference/configuration.md, "Physical bounds")."""

from __future__ import annotations

import math
from pathlib import Path

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from mpi_lidar.calibration.profile import FREQUENCY_BOUNDS_HZ, MAX_OFFSET_M, read_profile
from mpi_lidar.correction.options import (
    AMPLITUDE_SCALE_BOUNDS,
    MAX_AMPLITUDE_V2,
    MAX_BIAS_M,
    MAX_BLOCK_M,
    MAX_DEPTH_M,
    MAX_FOOTPRINT_AREA_M2,
    MAX_SIGMAS,
    NO_SATURATION_V2,
    CorrectionOptions,
)
from mpi_lidar.errors import MpiLidarError
from tests.cli_runner import assert_one_error_line, call_main

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
