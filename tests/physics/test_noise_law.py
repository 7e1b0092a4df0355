"""A scan's own noise law from the scatter of its frequencies, against laws put into the rows."""

from __future__ import annotations

import numpy as np
import pytest

from mpi_lidar.config import PAPER_FREQUENCIES_HZ, SensorConfig
from mpi_lidar.physics.noise import NoiseModel
from mpi_lidar.physics.noise_law import MIN_LAW_PIXELS, measure_noise_law

pytestmark = pytest.mark.unit

REFERENCE = NoiseModel.for_sensor(SensorConfig(), PAPER_FREQUENCIES_HZ)


def _rows(read_scale: float, shot_scale: float, n: int = 6000, seed: int = 0) -> np.ndarray:
    """Rows of one range each (1-20 m) whose depths scatter by exactly the law (read_scale, shot_scale) x the
    reference's, at amplitudes over three decades [V^2], with a fixed offset between the frequencies."""
    rng = np.random.default_rng(seed)
    amplitude = np.repeat(10 ** rng.uniform(-4, -1, (n, 1)), 4, axis=1) * np.array([1.0, 0.98, 1.01, 0.97])
    law = NoiseModel(REFERENCE.frequencies_hz, REFERENCE.speed_of_light_m_per_s,
                     read_scale * REFERENCE.read_variance_v4, shot_scale * REFERENCE.shot_variance_v2, 1.0,
                     REFERENCE.sensor)
    depth = rng.uniform(1, 20, (n, 1)) + rng.standard_normal((n, 4)) * law.depth_sigma_m(amplitude)
    return np.hstack([depth + np.array([0.0006, -0.0002, 0.0001, 0.0]), amplitude])


@pytest.mark.parametrize(("read_scale", "shot_scale"), [(1.0, 1.0), (0.0, 6.25), (40.0, 0.5)])
def test_measure_noise_law__finds_the_law_put_in_within_three_standard_errors(read_scale, shot_scale):
    law = measure_noise_law(_rows(read_scale, shot_scale), REFERENCE)
    assert law.significant and law.pixels == 6000
    assert abs(law.read_scale - read_scale) <= 3 * law.read_sigma + 1e-3
    assert abs(law.shot_scale - shot_scale) <= 3 * law.shot_sigma + 1e-3
    assert law.relative_sigma < 0.05


def test_measure_noise_law__a_unit_scales_the_read_term_by_its_square_and_the_shot_term_by_itself():
    rows = _rows(1.0, 1.0)
    counts = rows.copy()
    counts[:, 4:] *= 4000.0
    plain, scaled = measure_noise_law(rows, REFERENCE), measure_noise_law(counts, REFERENCE)
    # to rounding: a squared difference on the edge of the cut may fall the other way
    assert scaled.read_scale == pytest.approx(4000.0**2 * plain.read_scale, rel=1e-5)
    assert scaled.shot_scale == pytest.approx(4000.0 * plain.shot_scale, rel=1e-5)
    assert scaled.relative_sigma == pytest.approx(plain.relative_sigma, rel=1e-4)
    # the model it gives predicts the same depth noise for the same light, in either unit
    np.testing.assert_allclose(scaled.model(REFERENCE).depth_sigma_m(counts[:10, 4:]),
                               plain.model(REFERENCE).depth_sigma_m(rows[:10, 4:]), rtol=1e-5)


def test_measure_noise_law__wrong_wrap_counts_are_left_out():
    rows = _rows(1.0, 1.0)
    rows[:300, 3] += 4.797  # 5 % of the pixels a 31.25 MHz wrap off
    law = measure_noise_law(rows, REFERENCE)
    assert abs(law.shot_scale - 1.0) < 0.1 and abs(law.read_scale - 1.0) < 0.1


def test_measure_noise_law__too_few_pixels_or_no_scatter_is_not_significant():
    few = measure_noise_law(_rows(1.0, 1.0, n=MIN_LAW_PIXELS - 1), REFERENCE)
    assert not few.significant and "at least" in few.reason
    exact = _rows(0.0, 0.0)
    assert not measure_noise_law(exact, REFERENCE).significant
