"""The validity rules: no return, saturation, consistency in units of the noise, ranges past the ambiguity."""

from __future__ import annotations

import numpy as np
import pytest

from mpi_lidar.config import PAPER_FREQUENCIES_HZ, SensorConfig
from mpi_lidar.correction.options import CorrectionOptions, Flag
from mpi_lidar.correction.validity import BeyondAmbiguity, validity_flags
from mpi_lidar.physics.noise import NoiseModel
from mpi_lidar.physics.unwrap import combined_ambiguity_m

pytestmark = pytest.mark.unit

SENSOR = SensorConfig()
NOISE = NoiseModel.for_sensor(SENSOR, PAPER_FREQUENCIES_HZ)
# A shot-noise sensor with 2.5 x the sensor model's constant: no read noise, no floor but the light's own.
SHOT_ONLY = NoiseModel(NOISE.frequencies_hz, NOISE.speed_of_light_m_per_s, 0.0 * NOISE.read_variance_v4,
                       6.25 * NOISE.shot_variance_v2, 1.0, SENSOR)
AMBIGUITY_M = combined_ambiguity_m(PAPER_FREQUENCIES_HZ, SENSOR.speed_of_light_m_per_s)


def _rows(range_m: np.ndarray, albedo: float, noise: NoiseModel = NOISE, seed: int = 0) -> np.ndarray:
    """Rows of surfaces facing the sensor at ``range_m`` (n,) [m] (their true range; amplitudes from it),
    their depths given at ``range_m`` modulo nothing, with the noise of ``noise``."""
    rng = np.random.default_rng(seed)
    amplitude = np.repeat((SENSOR.gamma_r_v2 * albedo / range_m**2)[:, None], 4, axis=1)
    depth = range_m[:, None] + rng.standard_normal(amplitude.shape) * noise.depth_sigma_m(amplitude)
    return np.hstack([depth, amplitude])


def test_validity_flags__consistency_is_judged_in_units_of_the_noise_at_any_noise_level():
    noisy = SHOT_ONLY.scaled(4.0)  # ten times the sensor model's noise
    rows = _rows(np.full(20_000, 8.0), 0.5, noisy)
    options = CorrectionOptions()
    # judged by a law that knows the noise: chi-square's 1e-6 tail, not a fixed spread
    flagged = validity_flags(rows, options, noisy) == Flag.INCONSISTENT
    assert flagged.mean() < 1e-3
    assert (validity_flags(rows, options, SHOT_ONLY) == Flag.INCONSISTENT).mean() > 0.5, "a law that does not"
    off = rows[:5].copy()
    off[:, 3] += 0.5  # the least noisy frequency half a metre off: many times its noise
    assert (validity_flags(off, options, noisy) == Flag.INCONSISTENT).all()
    deprecated = CorrectionOptions(max_depth_spread_m=0.001)
    assert (validity_flags(rows[:100], deprecated, noisy) == Flag.INCONSISTENT).all()


def test_validity_flags__no_return_is_a_phase_noise_past_the_floor_and_zero_light():
    options = CorrectionOptions()
    floor = NOISE.floor_v2
    amplitude = np.array([0.0, 1e-3 * floor[0], 2 * floor[0], 20 * floor[0]])
    rows = np.hstack([np.full((4, 4), 2.0), np.repeat(amplitude[:, None], 4, axis=1)])
    flags = validity_flags(rows, options, NOISE)
    assert list(flags[:3]) == [Flag.NO_RETURN] * 3 and flags[3] != Flag.NO_RETURN
    assert (validity_flags(rows, options.model_copy(update={"min_amplitude_sigmas": 0.0}), NOISE)
            != Flag.NO_RETURN).all()


def test_validity_flags__saturation_only_from_levels_given():
    rows = _rows(np.full(10, 0.5), 1.0)
    assert not (validity_flags(rows, CorrectionOptions(), NOISE) == Flag.SATURATED).any()
    level = float(rows[0, 4]) * 0.9
    assert (validity_flags(rows, CorrectionOptions(saturation_amplitude_v2=level), NOISE) == Flag.SATURATED).all()
    per_frequency = np.array([np.inf, np.inf, np.inf, level])
    assert (validity_flags(rows, CorrectionOptions(), NOISE, saturation_v2=per_frequency) == Flag.SATURATED).all()


def test_validity_flags__a_bright_wall_past_the_ambiguity_is_flagged_a_dark_near_one_is_not():
    beyond = BeyondAmbiguity(AMBIGUITY_M, SENSOR.gamma_r_v2)
    far = _rows(np.full(2000, 26.0), 0.7, SHOT_ONLY)
    far[:, :4] -= AMBIGUITY_M  # its phases read it 24 m nearer, as the unwrapping gives it
    flags = validity_flags(far, CorrectionOptions(), SHOT_ONLY, beyond=beyond)
    assert (flags == Flag.BEYOND_AMBIGUITY).mean() > 0.99
    dark = _rows(np.linspace(0.5, 4.0, 2000), 0.03, SHOT_ONLY)
    near = validity_flags(dark, CorrectionOptions(), SHOT_ONLY, beyond=beyond)
    assert (near == Flag.BEYOND_AMBIGUITY).mean() < 0.01 and (near == Flag.NOT_NEEDED).mean() > 0.99
    assert not (validity_flags(far, CorrectionOptions(), SHOT_ONLY) == Flag.BEYOND_AMBIGUITY).any(), "none asked"


def test_validity_flags__no_return_counts_the_frequencies_light_together_unless_a_far_surface_could_give_it():
    options = CorrectionOptions()
    floor = NOISE.floor_v2
    weak = np.hstack([np.full((3, 4), 6.0), np.array([3.8, 3.3, 2.0])[:, None] * floor[None, :]])
    # 4 x 3.8^2 = 58 and 4 x 3.3^2 = 44 pass chi-square(8)'s quantile at exp(-5^2 / 2), 39.6; 4 x 2^2 = 16 does not
    flags = validity_flags(weak, options, NOISE)
    assert list(flags == Flag.NO_RETURN) == [False, False, True]
    # A 100 % wall at 30 m reads as this one at 6 m: where a surface past the ambiguity could give the amplitude,
    # each frequency must stand clear of its floor alone.
    beyond = BeyondAmbiguity(AMBIGUITY_M, SENSOR.gamma_r_v2)
    amplitude = SENSOR.gamma_r_v2 * 1.0 / 30.0**2
    far = np.hstack([np.full((1, 4), 6.0), np.full((1, 4), amplitude)])
    assert ((far[0, 4:] / floor) ** 2).sum() > 39.6 and (far[0, 4:] < 5 * floor).all(), "the example's premise"
    assert validity_flags(far, options, NOISE)[0] != Flag.NO_RETURN, "no unit: the joint rule"
    assert validity_flags(far, options, NOISE, beyond=beyond)[0] == Flag.NO_RETURN
    noisy = NOISE.scaled(1.5)  # 3.8 of its sds at 23 m read as a 71 % surface there, and as 296 % at 47 m
    near = np.hstack([np.full((1, 4), 23.0), 3.8 * noisy.floor_v2[None, :]])
    assert validity_flags(near, options, noisy, beyond=beyond)[0] != Flag.NO_RETURN
