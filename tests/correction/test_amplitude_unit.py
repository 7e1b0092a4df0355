"""A scan's amplitude unit read from the scatter of its frequencies (mpi_lidar.correction.amplitude_unit)."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from mpi_lidar.config import Config, SensorConfig
from mpi_lidar.correction.amplitude_unit import (
    LOG_SCALE_TOLERANCE,
    MIN_PIXELS,
    _chi_square_density,
    measure_amplitude_unit,
)
from mpi_lidar.physics.noise import NoiseModel
from mpi_lidar.simulation.scenes import corner, flat_wall, render

pytestmark = pytest.mark.unit


def TABLE_I(scan) -> NoiseModel:  # noqa: N802 - the sensor's name
    """The default sensor's noise model for the scan's frequencies."""
    return NoiseModel.for_sensor(SensorConfig(), scan.frequencies_hz)


def _in(scan, unit: float):
    return replace(scan, amplitude=(scan.amplitude * unit).astype(np.float32))


@pytest.mark.unit
@pytest.mark.parametrize("distance_m", [1.0, 3.0])
def test_measure_amplitude_unit__a_wall_in_any_unit_reads_that_unit_within_5_percent(distance_m):
    wall = render(flat_wall(20.0, distance_m, 0.7, height=40, width=48), Config(), np.random.default_rng(4),
                  patch_spacing_m=1.0)
    for unit in (1.0, 4000.0, 0.01):
        measured = measure_amplitude_unit(_in(wall, unit), TABLE_I(wall))
        assert measured.significant and measured.pixels > 1500
        assert measured.amplitude_scale / unit == pytest.approx(1.0, rel=0.05)
        assert 0 < measured.relative_sigma < 0.03


@pytest.mark.unit
def test_measure_amplitude_unit__reading_scales_exactly_with_the_unit():
    scan = render(corner(90.0, 2.0, 0.7, height=32, width=40), Config(), np.random.default_rng(5))
    one, counts = (measure_amplitude_unit(_in(scan, unit), TABLE_I(scan)) for unit in (1.0, 4096.0))
    # to the root finder's tolerance (LOG_SCALE_TOLERANCE in log lambda) on either reading
    assert counts.amplitude_scale / one.amplitude_scale == pytest.approx(4096.0, rel=2 * LOG_SCALE_TOLERANCE)


@pytest.mark.unit
def test_measure_amplitude_unit__a_noise_scale_is_taken_as_the_sensors():
    wall = render(flat_wall(20.0, 2.0, 0.7, height=40, width=48), Config(), np.random.default_rng(6),
                  patch_spacing_m=1.0)
    plain = measure_amplitude_unit(wall, TABLE_I(wall))
    noisier = measure_amplitude_unit(wall, NoiseModel.for_sensor(SensorConfig(), wall.frequencies_hz, 1.5))
    assert noisier.amplitude_scale < plain.amplitude_scale, "a noisier sensor explains the scatter at a smaller unit"


@pytest.mark.unit
def test_measure_amplitude_unit__too_few_consistent_pixels_is_not_significant():
    scan = render(flat_wall(20.0, 2.0, 0.7, height=5, width=8), Config(), np.random.default_rng(7),
                  patch_spacing_m=1.0)
    assert scan.shape[0] * scan.shape[1] < MIN_PIXELS
    measured = measure_amplitude_unit(scan, TABLE_I(scan))
    assert not measured.significant and np.isnan(measured.amplitude_scale) and "at least" in measured.reason


@pytest.mark.parametrize("dof", [1, 3, 7])
def test_chi_square_density__scipy_stats_value(dof):
    from scipy.stats import chi2

    for x in (0.1, 1.0, 2.366, 9.0):
        assert _chi_square_density(x, dof) == pytest.approx(float(chi2.pdf(x, dof)), rel=1e-12)
