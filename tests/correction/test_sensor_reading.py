"""The first stage: a scan's own noise law, its amplitude unit where its evidence allows, and saturation."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from mpi_lidar.config import Config, SensorConfig
from mpi_lidar.correction.options import CorrectionOptions
from mpi_lidar.correction.sensor_reading import read_sensor
from mpi_lidar.simulation.scenes import corner, flat_wall, render

pytestmark = pytest.mark.unit

SENSOR = SensorConfig()


@pytest.fixture(scope="module")
def wall():
    return render(flat_wall(20.0, 3.0, 0.7, height=48, width=64), Config(), np.random.default_rng(1),
                  patch_spacing_m=1.0)


def test_read_sensor__a_scan_in_v2_from_the_sensor_model_reads_its_law_and_v2(wall):
    reading = read_sensor(wall, SENSOR, CorrectionOptions())
    assert reading.unit_trusted and not reading.unit_given and reading.units_per_v2 == 1.0
    assert reading.law is not None and reading.law.significant and not reading.disagrees_with_reference
    # the law predicts the sensor model's depth noise at the wall's amplitudes within its own uncertainty
    amplitude = np.asarray(wall.amplitude).reshape(4, -1).T[:100].astype(np.float64)
    ratio = reading.noise.depth_sigma_m(amplitude) / _sensor_sigma(wall, amplitude)
    assert np.abs(np.median(ratio) - 1.0) < 3 * reading.law.relative_sigma + 0.02


def _sensor_sigma(scan, amplitude):
    from mpi_lidar.physics.noise import NoiseModel

    return NoiseModel.for_sensor(SENSOR, scan.frequencies_hz).depth_sigma_m(amplitude)


def test_read_sensor__a_noisier_sensor_is_read_as_such_not_as_another_unit():
    noisy = render(flat_wall(20.0, 3.0, 0.7, height=48, width=64), Config().replace(simulator={"noise_scale": 2.5}),
                   np.random.default_rng(2), patch_spacing_m=1.0)
    reading = read_sensor(noisy, SENSOR, CorrectionOptions())
    assert reading.unit_trusted and reading.units_per_v2 == 1.0, "2.5 x the noise is no unit"
    amplitude = np.asarray(noisy.amplitude).reshape(4, -1).T[:500].astype(np.float64)
    ratio = np.median(reading.noise.depth_sigma_m(amplitude) / _sensor_sigma(noisy, amplitude))
    assert ratio == pytest.approx(2.5, rel=0.1)
    assert reading.disagrees_with_reference and reading.noise_over_reference == pytest.approx(2.5, rel=0.1)
    profiled = read_sensor(noisy, SENSOR, CorrectionOptions(noise_scale=2.5))  # a profile that knows the noise
    assert not profiled.disagrees_with_reference and profiled.noise_over_reference == pytest.approx(1.0, rel=0.1)


@pytest.mark.parametrize(("unit", "said"), [(4000.0, "times what a white one does"), (0.01, "far smaller than V^2")])
def test_read_sensor__amplitudes_in_another_unit_contradict_v2_unless_given(wall, unit, said):
    scaled = replace(wall, amplitude=(wall.amplitude * unit).astype(np.float32))
    reading = read_sensor(scaled, SENSOR, CorrectionOptions())
    assert not reading.unit_trusted and said in reading.unit_contradiction
    given = read_sensor(scaled, SENSOR, CorrectionOptions(amplitude_scale=unit))
    assert given.unit_trusted and given.unit_given and given.units_per_v2 == unit
    plain = read_sensor(wall, SENSOR, CorrectionOptions())
    assert given.law.shot_scale == pytest.approx(plain.law.shot_scale, rel=1e-4), "the same law in V^2"
    wrong = read_sensor(scaled, SENSOR, CorrectionOptions(amplitude_scale=1.0))
    assert not wrong.unit_trusted and wrong.unit_contradiction.startswith("with the unit given (1 per V^2)")


def test_read_sensor__a_plateau_of_clipped_amplitudes_is_saturation_and_nothing_else_is():
    scan = render(corner(90.0, 1.0, 0.9, height=40, width=48), Config(), np.random.default_rng(3))
    plain = read_sensor(scan, SENSOR, CorrectionOptions())
    assert np.isinf(plain.saturation_v2).all(), "a scan without clipped amplitudes saturates nowhere"
    level = np.float32(np.percentile(scan.amplitude[-1], 90))
    clipped = replace(scan, amplitude=np.minimum(scan.amplitude, level))
    reading = read_sensor(clipped, SENSOR, CorrectionOptions())
    assert reading.saturation_v2[-1] == pytest.approx(float(level), rel=1e-5)
    given = read_sensor(scan, SENSOR, CorrectionOptions(saturation_amplitude_v2=0.5))
    np.testing.assert_array_equal(given.saturation_v2, 0.5)


def _sensor_scan(range_m: np.ndarray, albedo: float, read_scale: float, shot_scale: float, seed: int = 0):
    """A scan of surfaces facing the scanner at ``range_m`` (H, W) [m] from a sensor whose law is (read_scale,
    shot_scale) x the sensor model's, wrapped with the physical speed of light, amplitudes in V^2."""
    from mpi_lidar.constants import SPEED_OF_LIGHT_M_PER_S
    from mpi_lidar.physics.noise import NoiseModel
    from mpi_lidar.scans.scan import Scan

    frequencies = Config().frequencies_hz
    reference = NoiseModel.for_sensor(SENSOR, frequencies)
    law = NoiseModel(frequencies, SPEED_OF_LIGHT_M_PER_S, read_scale * reference.read_variance_v4,
                     shot_scale * reference.shot_variance_v2, 1.0, SENSOR)
    rng = np.random.default_rng(seed)
    f, (h, w) = len(frequencies), range_m.shape
    light = np.repeat((SENSOR.gamma_r_v2 * albedo / range_m**2).reshape(1, -1), f, axis=0).T  # (n, F)
    amplitude = np.abs(light + rng.standard_normal(light.shape) * law.quadrature_sigma_v2(light))
    depth = range_m.reshape(-1, 1) + rng.standard_normal(light.shape) * law.depth_sigma_m(light)
    period = SPEED_OF_LIGHT_M_PER_S / (2 * np.asarray(frequencies))
    wrapped = np.mod(depth, period).T.reshape(f, h, w).astype(np.float32)
    return Scan(name="made", frequencies_hz=frequencies, depth=wrapped,
                amplitude=amplitude.T.reshape(f, h, w).astype(np.float32), azimuth_rad=np.linspace(-0.15, 0.15, w),
                elevation_rad=np.linspace(-0.15, 0.15, h), speed_of_light_m_per_s=SPEED_OF_LIGHT_M_PER_S)


@pytest.mark.parametrize("ranges", ["wall at 12 m", "ramp 0.5-23 m"])
def test_read_sensor__a_read_noise_sensor_in_a_hundredfold_smaller_unit_is_quieter_than_any_sensor(ranges):
    range_m = np.full((32, 32), 12.0) if ranges.startswith("wall") else np.repeat(
        np.linspace(0.5, 23.0, 32)[None], 32, axis=0)
    scan = _sensor_scan(range_m, 0.7, 2.0, 0.3)
    assert read_sensor(scan, SENSOR, CorrectionOptions()).unit_trusted
    # amplitude x range^2 reads as a dark surface (0.007) near by, or as a plausible one past the 24 m ambiguity:
    # only the noise tells, 70 times below the sensor model's no-light noise
    small = read_sensor(replace(scan, amplitude=scan.amplitude * np.float32(0.01)), SENSOR, CorrectionOptions())
    assert not small.unit_trusted and "quieter than any sensor's" in small.unit_contradiction


@pytest.mark.parametrize(("range_m", "albedo", "law"), [(26.0, 0.9, (0.0, 6.25)), (30.0, 0.9, (1.0, 1.0)),
                                                        (40.0, 0.3, (1.0, 1.0)), ("0.5-4", 0.03, (0.0, 6.25))])
def test_read_sensor__dark_scenes_in_v2_read_as_v2_even_without_read_noise(range_m, albedo, law):
    """Past the 24 m ambiguity (surfaces read as 1.5-15 % albedo near by) or dark near by (3 %), from a sensor
    without read noise (2.5 x the model's shot noise) or the model's own: V^2."""
    ranges = np.repeat(np.linspace(0.5, 4.0, 32)[None], 32, axis=0) if range_m == "0.5-4" else np.full(
        (32, 32), range_m)
    reading = read_sensor(_sensor_scan(ranges, albedo, *law), SENSOR, CorrectionOptions())
    assert reading.unit_trusted, reading.unit_contradiction


def test_read_sensor__a_sensor_ten_times_noisier_reads_as_v2_and_a_unit_4000_times_larger_does_not():
    scan = _sensor_scan(np.full((32, 32), 8.0), 0.7, 200.0, 30.0)  # ten times a read-dominated law's sd
    reading = read_sensor(scan, SENSOR, CorrectionOptions())
    assert reading.unit_trusted and reading.noise_over_reference > 10, reading.unit_contradiction
    counts = read_sensor(replace(scan, amplitude=scan.amplitude * np.float32(4000)), SENSOR, CorrectionOptions())
    assert not counts.unit_trusted
