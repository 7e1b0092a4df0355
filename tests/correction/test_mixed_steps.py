"""The mixed-pixel stage's step test: a footprint between two flat sides is mixed even where its two returns are
equally bright (its depth the sides' mean, its frequencies in agreement), a grazing or kinked surface is not; and
the two-return fit at a frequency set that is not evenly spaced."""

from __future__ import annotations

import numpy as np
import pytest

from mpi_lidar.config import Config, SensorConfig
from mpi_lidar.correction.gating import GateDecision
from mpi_lidar.correction.mixed import (
    MIN_EDGE_M,
    STEP_SIGMAS,
    _stepped,
    amplitude_spread,
    find_mixed,
    frequency_gains,
)
from mpi_lidar.correction.options import CorrectionOptions, Flag
from mpi_lidar.correction.tiles import scan_tiles
from mpi_lidar.correction.validity import check_validity
from mpi_lidar.physics.noise import NoiseModel
from mpi_lidar.simulation.scenes import scan_from_phasors

pytestmark = pytest.mark.unit

EDGE_COLUMN = 6
H, W = 14, 14


def _scan(surfaces, config: Config, seed: int = 0):
    """A scan whose column c's phasor is the sum of ``surfaces(c)``'s returns, (range [m], albedo, share)."""
    freqs = np.asarray(config.frequencies_hz)
    w = 4 * np.pi * freqs / config.sensor.speed_of_light_m_per_s
    columns = np.zeros((freqs.size, W), np.complex128)
    for column in range(W):
        for range_m, albedo, share in surfaces(column):
            columns[:, column] += share * config.sensor.gamma_r_v2 * albedo / range_m**2 * np.exp(1j * w * range_m)
    phasor = np.broadcast_to(columns[:, None, :], (freqs.size, H, W))
    return scan_from_phasors("steps", phasor, config, np.random.default_rng(seed))


def _mixed(scan):
    noise = NoiseModel.for_sensor(SensorConfig(), scan.frequencies_hz)
    tiles = scan_tiles(scan, 4 * scan.shape[1])  # several tiles: the sides two rows out cross them
    validity = check_validity(scan, noise, CorrectionOptions(), tiles)
    flags = np.where(validity.flags == Flag.NOT_NEEDED, np.uint8(Flag.NO_MULTIPATH), validity.flags)
    result = find_mixed(validity.scan, tiles, validity, GateDecision(flags.astype(np.uint8), 0, served=True), noise)
    return result, result.decision.flags.reshape(scan.shape), validity


def _plate(plate_m, plate_albedo, wall_m, wall_albedo, share):
    def surfaces(column):
        if column < EDGE_COLUMN:
            return [(plate_m, plate_albedo, 1.0)]
        if column > EDGE_COLUMN:
            return [(wall_m, wall_albedo, 1.0)]
        return [(plate_m, plate_albedo, share), (wall_m, wall_albedo, 1 - share)]

    return surfaces


@pytest.mark.parametrize(("plate_albedo", "wall_m", "wall_albedo", "share"),
                         [(0.5, 2.2, 0.605, 0.5), (0.2, 2.5, 0.8, 0.7), (0.2, 4.0, 0.8, 0.5)])
def test_find_mixed__a_footprint_between_two_flat_sides_is_mixed_however_equal_its_returns(
        plate_albedo, wall_m, wall_albedo, share):
    """Returns of equal light (the wall's albedo times its range squared over the plate's), gaps of 0.2-2 m."""
    _, flags, validity = _mixed(_scan(_plate(2.0, plate_albedo, wall_m, wall_albedo, share), Config()))
    measured = validity.measured_depth.reshape(flags.shape)[:, EDGE_COLUMN]
    assert np.all((measured > 2.05) & (measured < wall_m - 0.05)), "a flying point 5 cm or more from both"
    assert np.isin(flags[2:-2, EDGE_COLUMN], [Flag.MIXED, Flag.TWO_RETURNS]).all()
    others = [c for c in range(W) if c != EDGE_COLUMN]
    assert not np.isin(flags[:, others], [Flag.MIXED, Flag.TWO_RETURNS]).any()


@pytest.mark.parametrize("slopes", [(0.12, 0.12), (0.02, 0.15), (0.15, 0.02), (0.03, 0.3)])
def test_find_mixed__a_grazing_or_kinked_surface_is_not_mixed(slopes):
    """A surface whose depth climbs 12-30 cm a pixel (a jump of many noise sigmas), straight or kinked at the
    edge column as a corner is: every pixel one surface, none flagged."""
    def surfaces(column):
        depth = 2.0 + slopes[0] * min(column, EDGE_COLUMN) + slopes[1] * max(column - EDGE_COLUMN, 0)
        return [(depth, 0.8, 1.0)]

    result, flags, _ = _mixed(_scan(surfaces, Config()))
    assert result.mixed_pixels == result.resolved_pixels == 0 and not np.isin(flags, [Flag.MIXED]).any()


def test_stepped__between_two_flat_sides_in_units_of_the_noise():
    row = np.array([2.0, 2.0, 2.0, 2.1, 2.2, 2.2, 2.2], np.float32)
    depth = np.tile(row, (5, 1))
    quiet = np.full(depth.shape, 0.002, np.float32)
    found = _stepped(depth, quiet)
    assert found[:, 3].all() and found.sum() == depth.shape[0]
    # the same step under noise of 2 cm: 10 cm is less than STEP_SIGMAS of it
    assert STEP_SIGMAS * np.hypot(0.02, 0.02) > 0.1 and not _stepped(depth, np.full(depth.shape, 0.02)).any()
    only = np.zeros(depth.shape, bool)
    only[2, 3] = True
    assert np.array_equal(_stepped(depth, quiet, only), only), "only the pixels asked about"
    # a side that is not flat (a ramp into the step), a jump under MIN_EDGE_M, or the pixel not between its sides
    assert not _stepped(np.tile(np.array([1.9, 1.97, 2.05, 2.1, 2.2, 2.2, 2.2], np.float32), (5, 1)), quiet).any()
    assert not _stepped(np.tile(row * 0.2, (5, 1)), quiet).any() and MIN_EDGE_M > 0.02
    assert not _stepped(np.tile(np.array([2.0, 2.0, 2.0, 2.3, 2.2, 2.2, 2.2], np.float32), (5, 1)), quiet).any()


def test_find_mixed__resolves_two_returns_at_frequencies_not_evenly_spaced():
    config = Config(frequencies_hz=(10e6, 20e6, 25e6, 40e6))
    result, flags, _ = _mixed(_scan(_plate(2.0, 0.1, 9.0, 1.0, 0.5), config))
    resolved = flags == Flag.TWO_RETURNS
    assert resolved[:, EDGE_COLUMN].mean() > 0.8 and result.second_returns is not None
    np.testing.assert_allclose(result.validity.usable_depth.reshape(flags.shape)[resolved], 2.0, atol=0.05)
    np.testing.assert_allclose(result.second_returns.depth_m[resolved], 9.0, atol=0.3)


def test_amplitude_spread__chi_square_of_one_surface_and_two_returns_beating():
    """One surface's amplitudes, noisy, give chi^2(F - 1) (mean 3, 1e-4 quantile 21.1); two equal returns 2 m
    apart beat by cos(2 pi f g / c) over the frequencies, hundreds of sigmas; a scanner's gains, read from each
    pixel's neighbours, are divided out."""
    config = Config()
    noise = NoiseModel.for_sensor(SensorConfig(), config.frequencies_hz)
    rng = np.random.default_rng(1)
    light = np.full((40, 50, 4), 0.02)
    noisy = light + noise.quadrature_sigma_v2(light) * rng.standard_normal(light.shape)
    ys, xs = (index.ravel() for index in np.mgrid[1:39, 1:49])
    spread = amplitude_spread(noisy[ys, xs], 1.0, noise)
    assert 2.7 < spread.mean() < 3.3 and (spread > 21.1).mean() < 2e-3
    scanner = np.array([1.1, 1.0, 0.95, 0.9])
    gains = frequency_gains(noisy * scanner, ys, xs)
    np.testing.assert_allclose(gains, np.broadcast_to(scanner / scanner.mean(), gains.shape), rtol=5e-3)
    assert amplitude_spread(noisy[ys, xs] * scanner, gains, noise).mean() < 4.0, "the gains divided out"
    freqs = np.asarray(config.frequencies_hz)
    beat = np.abs(np.cos(2 * np.pi * freqs * 2.0 / config.sensor.speed_of_light_m_per_s)) * 0.02
    assert amplitude_spread(beat[None, :], 1.0, noise)[0] > 1e3
