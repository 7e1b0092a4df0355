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
