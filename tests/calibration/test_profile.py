"""The sensor profile (mpi_lidar.calibration.profile): written and read back, checked, and the options and
simulation sections it gives."""

from __future__ import annotations

import pytest
from pydantic import ValidationError

from mpi_lidar.calibration.profile import (
    RANGE_MARGIN,
    SensorProfile,
    profile_options,
    read_profile,
    write_profile,
)
from mpi_lidar.correction.footprint import EstimateMethod, FootprintEstimate
from mpi_lidar.errors import MpiLidarError

pytestmark = pytest.mark.unit

FREQS = (12.5e6, 18.75e6, 25e6, 31.25e6)


def measured_profile() -> SensorProfile:
    """A profile with every measured field."""
    return SensorProfile.model_validate({
        "footprint_area_m2": 0.02, "amplitude_scale": 4000.0, "frequencies_hz": FREQS, "noise_scale": 1.2,
        "range_m": (0.6, 7.5), "frequency_offsets_m": (-5e-4, -2e-4, 0.0, 0.0), "window_leakage_removed": False})


def test_profile__round_trip_and_no_overwrite(tmp_path):
    pooled = FootprintEstimate(0.02, 0.001, 900, 2, (EstimateMethod.REFERENCE,), 3)
    profile = SensorProfile.from_estimate(pooled, ["a", "b"], saturation_amplitude_v2=0.5, min_amplitude_sigmas=4.0,
                                          frequency_offsets_m=(-1e-4, 0.0), window_leakage_removed=True)
    path = write_profile(profile, tmp_path / "sensor.toml")
    assert read_profile(path) == profile and read_profile(path).window_leakage_removed is True
    with pytest.raises(MpiLidarError, match="already exists"):
        write_profile(profile, path)
    assert read_profile(path) == profile


def test_profile__speed_of_light_and_each_scans_values_round_trip(tmp_path):
    pooled = FootprintEstimate(0.02, 0.001, 900, 2, (EstimateMethod.REFERENCE,), 3)
    profile = SensorProfile.from_estimate(pooled, ["a"], ["a: 0.02 m^2; c = 299792458 m/s"],
                                          speed_of_light_m_per_s=299_792_458.0)
    back = read_profile(write_profile(profile, tmp_path / "sensor.toml"))
    assert back == profile and back.speed_of_light_m_per_s == 299_792_458.0
    assert back.calibration is not None and back.calibration["scans"] == ["a: 0.02 m^2; c = 299792458 m/s"]
    assert "speed_of_light_m_per_s = 299792458.0" in (tmp_path / "sensor.toml").read_text()


@pytest.mark.parametrize("c", [3e5, 3.2e8, 3])
def test_read_profile__a_speed_of_light_out_of_bounds_is_refused(tmp_path, c):
    path = tmp_path / "sensor.toml"
    path.write_text(f"footprint_area_m2 = 0.02\nspeed_of_light_m_per_s = {c}\n")
    with pytest.raises(MpiLidarError, match=r"is invalid \(.*speed_of_light_m_per_s"):
        read_profile(path)


def test_from_estimate__none_leaves_a_field_out_and_the_sources_are_recorded():
    pooled = FootprintEstimate(0.02, 0.001, 900, 2, (EstimateMethod.REFERENCE,), 3)
    profile = SensorProfile.from_estimate(pooled, ["a"], noise_scale=None, range_m=(1.0, 2.0))
    assert profile.footprint_area_m2 == 0.02 and profile.noise_scale is None and profile.range_m == (1.0, 2.0)
    assert profile.calibration is not None and profile.calibration["sources"] == ["a"]
    assert "area_m2" not in profile.calibration  # the area is the profile's own field


def test_read_profile__a_missing_file_names_the_command_that_writes_one(tmp_path):
    with pytest.raises(MpiLidarError, match="does not exist; write one with mpi-lidar calibrate"):
        read_profile(tmp_path / "sensor.toml")


@pytest.mark.parametrize(("text", "fragment"), [("footprint_area_m2 = \n", "is not valid TOML"),
                                                ("footprint_area_m2 = -1.0\n", "is invalid"),
                                                ("footprint = 0.02\n", "is invalid")])
def test_read_profile__a_bad_file_is_one_line_naming_it(tmp_path, text, fragment):
    path = tmp_path / "sensor.toml"
    path.write_text(text)
    with pytest.raises(MpiLidarError, match=fragment) as caught:
        read_profile(path)
    assert str(path) in str(caught.value) and "\n" not in str(caught.value)


@pytest.mark.parametrize(("fields", "fragment"), [
    ({"range_m": (2.0, 1.0)}, "near < far"),
    ({"frequencies_hz": (25e6, 25e6)}, "duplicates"),
    ({"frequencies_hz": FREQS, "frequency_offsets_m": (0.0, 0.0)}, "one per frequency"),
])
def test_sensor_profile__inconsistent_fields_are_refused(fields, fragment):
    with pytest.raises(ValidationError, match=fragment):
        SensorProfile.model_validate({"footprint_area_m2": 0.02, **fields})


def test_profile_options__none_sets_nothing_and_a_profile_its_values_and_hash(tmp_path):
    assert profile_options(None) == {}
    profile = measured_profile()
    path = write_profile(profile, tmp_path / "sensor.toml")
    given = profile_options(path)["sensor_profile"]
    digest = profile.record()["sha256"]
    assert given == {**profile.options(), **profile.noise_options(), "sensor_profile_sha256": digest}
    assert given["amplitude_scale"] == 4000.0 and given["noise_scale"] == 1.2
    assert given["frequency_offsets_m"] == (-5e-4, -2e-4, 0.0, 0.0) and given["window_leakage_removed"] is False


def test_noise_options__leakage_is_said_only_with_offsets():
    bare = SensorProfile.model_validate({"footprint_area_m2": 0.02, "window_leakage_removed": True})
    assert bare.noise_options() == {}


def test_simulation__the_sensor_s_frequencies_noise_and_widened_range():
    sections = measured_profile().simulation()
    assert sections["frequencies_hz"] == FREQS and sections["simulator"] == {"noise_scale": 1.2}
    assert sections["prior"] == {"d_as_m": (0.6 * (1 - RANGE_MARGIN), 7.5 * (1 + RANGE_MARGIN)),
                                 "d_as_distribution": "log_uniform"}
    assert SensorProfile.model_validate({"footprint_area_m2": 0.02}).simulation() == {}


def test_record__the_hash_follows_the_values():
    profile = measured_profile()
    other = profile.model_copy(update={"noise_scale": 1.3})
    assert profile.record()["sha256"] == measured_profile().record()["sha256"] != other.record()["sha256"]
