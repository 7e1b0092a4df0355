"""Physical quantities of sensor profiles and correction options: strict numbers within documented bounds.

A boolean is no number of square metres, and a footprint of 1e9 m^2 no footprint: each is refused with one
line naming the field and its bound (docs/reference/configuration.md, "Physical bounds")."""

from __future__ import annotations

import math
import re
import types
import typing
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import zarr
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from mpi_lidar.calibration.profile import (
    FREQUENCY_BOUNDS_HZ,
    MAX_OFFSET_M,
    PER_FREQUENCY_FIELDS,
    SensorProfile,
    check_profile_frequencies,
    profile_options,
    read_profile,
)
from mpi_lidar.config import SensorConfig
from mpi_lidar.correction.baseline import PER_FREQUENCY_OPTIONS
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
from mpi_lidar.correction.validity import validity_flags
from mpi_lidar.errors import MpiLidarError
from mpi_lidar.physics.noise import NoiseModel
from mpi_lidar.scans.scan import ScanError, check_wrap_periods, lowest_depth_m, validate
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
    ({"depth": np.asarray(SCAN.depth) - 13.0}, "never by more than 1.15 m"),
    ({"depth": np.asarray(SCAN.depth) - 13.0, "depth_wrapped": False}, "never by more than 1.15 m"),
    ({"depth": np.asarray(SCAN.depth) + 2.9}, "beyond that frequency's wrap period 4.8000 m"),
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


# --- fields of one value per frequency: checked where a profile or the options meet the scan -------------------


def _variable_tuple(annotation: object) -> bool:
    """Whether the annotation is, under Optional and Annotated, a tuple of any length (``tuple[float, ...]``)."""
    if typing.get_origin(annotation) in (typing.Union, types.UnionType):
        return any(_variable_tuple(member) for member in typing.get_args(annotation))
    if typing.get_origin(annotation) is typing.Annotated:
        return _variable_tuple(typing.get_args(annotation)[0])
    return typing.get_origin(annotation) is tuple and typing.get_args(annotation)[-1:] == (Ellipsis,)


@pytest.mark.unit
@pytest.mark.parametrize(("model", "declared"), [(CorrectionOptions, PER_FREQUENCY_OPTIONS),
                                                 (SensorProfile, PER_FREQUENCY_FIELDS)])
def test_per_frequency__every_field_of_any_length_is_declared_and_checked(model, declared):
    of_any_length = {name for name, field in model.model_fields.items() if _variable_tuple(field.annotation)}
    assert of_any_length == set(declared)


@pytest.mark.unit
def test_correct_scan__a_profiles_offsets_for_other_frequencies_are_one_line_not_an_index_error(tmp_path, raw_model):
    """Through the Python API, with no model card to check the profile against: the scan's own frequencies."""
    from mpi_lidar.correction.correct import correct_scan
    from mpi_lidar.learning.model import load_model

    sensor = tmp_path / "sensor.toml"
    sensor.write_text(PROFILE + "frequency_offsets_m = [0.001, 0.0]\n")
    options = CorrectionOptions.from_cli(**profile_options(sensor))
    fragment = "give 2 frequency_offsets_m for the 4 frequencies of scan bounds"
    with pytest.raises(MpiLidarError, match=fragment) as refused:
        correct_scan(SCAN, load_model(raw_model), options)
    assert "\n" not in str(refused.value) and not isinstance(refused.value, IndexError)
    options = options.model_copy(update={"frequency_offsets_m": (0.001, 0.0, 0.0, 0.0)})
    assert correct_scan(SCAN, load_model(raw_model), options).frequency_offsets_m == (0.001, 0.0, 0.0, 0.0)


@pytest.mark.unit
def test_check_profile_frequencies__each_per_frequency_field_one_value_per_frequency(tmp_path):
    sensor = tmp_path / "sensor.toml"
    sensor.write_text(PROFILE + "frequencies_hz = [1.25e7, 1.875e7]\n")
    with pytest.raises(MpiLidarError, match=re.escape("calibrated at 12.5, 18.75 MHz")):
        check_profile_frequencies(read_profile(sensor), (12.5e6, 18.75e6, 25e6, 31.25e6), "the scan", sensor)
    check_profile_frequencies(read_profile(sensor), (12.5e6, 18.75e6), "the scan", sensor)


# --- depths: at least -3 sigma of each pixel's own noise, below the wrap period ---------------------------------


@pytest.mark.unit
def test_lowest_depth_m__three_deviations_of_the_weakest_return_at_the_lowest_frequency():
    # c / (4 pi f) / SNR at 12.5 MHz, c = 3e8: 1.9099 m / 5 = 0.38197 m; three of them.
    assert lowest_depth_m((31.25e6, 12.5e6), 3e8) == pytest.approx(-3 * 3e8 / (4 * math.pi * 12.5e6) / 5, rel=1e-12)
    assert lowest_depth_m((12.5e6,), 3e8) == pytest.approx(-1.14592, abs=1e-5)


@pytest.mark.unit
@pytest.mark.parametrize("wrapped", [True, False])
def test_scan_store__a_near_surface_slightly_negative_within_its_noise_is_read(tmp_path, wrapped):
    """A row at 2 mm before the scanner's zero, by its noise: no reason to refuse the scan, wrapped or not."""
    depth = np.asarray(SCAN.depth).copy()
    depth[:, 0, :] = -0.002
    path = write_scan(replace(SCAN, depth=depth, depth_wrapped=wrapped), tmp_path / "near.scan.zarr")
    assert float(np.min(read_scan(path).depth)) == pytest.approx(-0.002, abs=1e-7)


@pytest.mark.unit
def test_scan_store__an_unwrapped_depth_may_pass_the_wrap_period():
    """The scanner unwrapped them: past 4.8 m at 31.25 MHz is a range, not a wrong period."""
    far = replace(SCAN, depth=np.asarray(SCAN.depth) + 2.9, depth_wrapped=False)
    check_wrap_periods(validate(far, "far"), "far")


@pytest.mark.unit
def test_validity_flags__a_depth_more_than_three_of_its_own_deviations_below_zero_is_inconsistent():
    frequencies = (12.5e6, 18.75e6, 25e6, 31.25e6)
    noise = NoiseModel.for_sensor(SensorConfig(), frequencies)
    amplitude = np.full((1, 4), 0.05)
    sigma = noise.depth_sigma_m(amplitude)[0]  # each frequency's own deviation at this amplitude [m]
    rows = np.concatenate([np.stack([-2.5 * sigma, -3.5 * sigma, 0.5 * sigma, -3.5 * sigma * np.eye(4)[0]]),
                           np.repeat(amplitude, 4, axis=0)], axis=1)
    flags = validity_flags(rows, CorrectionOptions(), noise)
    assert [Flag(flag) for flag in flags[:2]] == [Flag.NOT_NEEDED, Flag.INCONSISTENT]
    assert Flag(flags[2]) == Flag.NOT_NEEDED  # at +0.5 sigma, each frequency: a near surface
    assert Flag(flags[3]) == Flag.INCONSISTENT  # one frequency alone 3.5 of its deviations below zero


# --- classes of bad data end with their own reason, and every depth with its uncertainty ---------------------------


@pytest.mark.unit
def test_correct_scan__amplitudes_all_zero_are_no_return_in_every_pixel(raw_model):
    from mpi_lidar.correction.correct import correct_scan
    from mpi_lidar.learning.model import load_model

    correction = correct_scan(replace(SCAN, amplitude=np.zeros_like(SCAN.amplitude)), load_model(raw_model))
    assert (correction.flags == Flag.NO_RETURN).all()
    assert np.isnan(correction.depth).all()


@pytest.mark.unit
@pytest.mark.parametrize("change", [{}, {"amplitude": np.asarray(SCAN.amplitude) * 30},
                                    {"depth": np.asarray(SCAN.depth) + 4.0, "depth_wrapped": False}],
                         ids=["as-is", "units-contradicted", "out-of-range"])
def test_correct_scan__every_pixel_with_a_depth_has_its_uncertainty(raw_model, change):
    """Served, unserved for its amplitudes' units, or beyond the model's range: a depth never comes alone."""
    from mpi_lidar.correction.correct import correct_scan
    from mpi_lidar.learning.model import load_model

    correction = correct_scan(replace(SCAN, **change), load_model(raw_model))
    assert correction.uncertainty_m is not None
    has_depth = np.isfinite(correction.depth)
    assert has_depth.any()
    assert np.isfinite(correction.uncertainty_m[has_depth]).all() and (correction.uncertainty_m[has_depth] > 0).all()
