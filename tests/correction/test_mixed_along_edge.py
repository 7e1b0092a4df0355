"""The mixed-pixel stage along the edge: a line of mixed pixels whose one mixture lies a few of a pixel's noise
sigmas off the nearer side (equal returns a few tenths of a metre apart at 10 m) is found by the median of each
pixel and its two neighbours along the edge, and one whose weak far return metres behind moves its depth a few
centimetres by the three's phasors fitted together; a side's own pixels, and clean walls at 10 m, are not."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from mpi_lidar.config import Config, SensorConfig
from mpi_lidar.correction import _mixed_ranges as ranges
from mpi_lidar.correction._mixed_steps import BLOCK_REACH, stepped
from mpi_lidar.correction.options import Flag
from mpi_lidar.physics.noise import NoiseModel
from mpi_lidar.simulation.scenes import flat_wall, render, scan_from_phasors
from tests.correction.mixed_stage import mixed_stage

pytestmark = pytest.mark.unit

CONFIG = Config()
H, W = 20, 24
EDGE_ROW = 10
SIGMA_M = 0.025  # a pixel's fused noise at 10 m, albedo 0.5 [m]


def _flags(scan):
    """The stage's flags (H, W), read in tiles of four rows, and whether the gate's decision came back as it was."""
    result, decision, flags, validity = mixed_stage(scan)
    return flags, result.decision is decision, validity


def _edge_scan(gap_m: float, seed: int):
    """A plate (0.5) at 10 m above a wall (0.5) ``gap_m`` behind it, the row between holding three quarters of
    plate (as where a plate's edge falls a quarter pitch inside a footprint), each pixel's phasor the sum."""
    freqs = np.asarray(CONFIG.frequencies_hz)
    w = 4 * np.pi * freqs / CONFIG.sensor.speed_of_light_m_per_s
    gamma = CONFIG.sensor.gamma_r_v2
    plate, wall = (gamma * 0.5 / r**2 * np.exp(1j * w * r) for r in (10.0, 10.0 + gap_m))
    share = np.where(np.arange(H) < EDGE_ROW, 1.0, 0.0)
    share[EDGE_ROW] = 0.75
    phasor = share[None, :, None] * plate[:, None, None] + (1 - share)[None, :, None] * wall[:, None, None]
    return scan_from_phasors("edge", np.broadcast_to(phasor, (freqs.size, H, W)), CONFIG,
                             np.random.default_rng(seed))


def test_find_mixed__equal_returns_a_third_of_a_metre_apart_at_10_m_are_flagged_along_the_edge():
    """The edge row's mixture lies 7 cm behind the plate: 2.5 of one pixel's noise with the plate's level's, which
    the pixel alone often misses, but 4 of its level along the edge. Of the row's pixels more than 5 cm from both
    surfaces in four scans at least 90 % are flagged (82 % were without the level along the edge); a side's pixel
    is flagged at most once a scan (a noisy one beside the edge, as before)."""
    flying, flagged = [], []
    for seed in range(4):
        scan = _edge_scan(0.3, seed)
        flags, _, validity = _flags(scan)
        depth = validity.measured_depth.reshape(H, W)[EDGE_ROW, 3:-3]
        off = np.minimum(np.abs(depth - 10.0), np.abs(depth - 10.3)) > 0.05
        flying.append(off)
        flagged.append(np.isin(flags[EDGE_ROW, 3:-3], [Flag.MIXED, Flag.TWO_RETURNS]))
        assert np.isin(np.delete(flags, EDGE_ROW, axis=0), [Flag.MIXED, Flag.TWO_RETURNS]).sum() <= 1
    off, found = np.concatenate(flying), np.concatenate(flagged)
    assert off.sum() >= 50 and found[off].mean() >= 0.9


def test_stepped__a_line_of_mixed_pixels_a_few_sigmas_off_the_nearer_side():
    """Sides 0.3 m apart at 10 m, the edge row 7 cm off the nearer: found in most of the row (under 80 % without
    its level along the edge); a side's row beside it, whose neighbours along the edge lie on its level, is not."""
    rows = np.where(np.arange(H) < EDGE_ROW, 10.0, 10.3)
    rows[EDGE_ROW] = 10.07
    found = []
    for seed in range(3):
        depth = (rows[:, None] + SIGMA_M * np.random.default_rng(seed).standard_normal((H, W))).astype(np.float32)
        flags = stepped(depth, np.full(depth.shape, SIGMA_M, np.float32))
        inner = flags[BLOCK_REACH:-BLOCK_REACH, BLOCK_REACH:-BLOCK_REACH]
        found.append(flags[EDGE_ROW, BLOCK_REACH:-BLOCK_REACH])
        assert inner.sum() == found[-1].sum(), "only the edge row"
    assert np.concatenate(found).mean() > 0.85


@pytest.mark.parametrize("tilt_deg", [0.0, 30.0, 60.0])
def test_find_mixed__a_clean_wall_at_10_m_is_left_as_the_gate_left_it(tilt_deg):
    """A wall at 10 m, square or turned, filling the view (no silhouette): its noisy pixels step by centimetres
    and the turned ones' rows climb alike, but no side is flat beyond its noise with a level along the edge off
    it: no pixel is mixed, and the gate's decision comes back as it went in."""
    wall = flat_wall(tilt_deg, 10.0, height=24, width=32)
    wall = replace(wall, azimuth_rad=0.4 * wall.azimuth_rad, elevation_rad=0.4 * wall.elevation_rad)
    for seed in range(3):
        scan = render(wall, CONFIG, np.random.default_rng(seed), patch_spacing_m=0.5)
        flags, unchanged, _ = _flags(scan)
        assert not np.isin(flags, [Flag.MIXED, Flag.TWO_RETURNS]).any() and unchanged


def _column(near_share: float, seed: int) -> tuple[np.ndarray, ...]:
    """Sides at 10 m (left of column 8) and 15 m (right), 3 cm of noise; column 8's phasors (H, F) ``near_share`` of
    an amplitude of 0.0005 V^2 at 10 m and the rest at 15 m, with the sensor model's noise, and that noise; its
    depth the best single range; the pixels asked about (column 8 within BLOCK_REACH of no border); each pixel's
    row in the phasors (column 8's rows, -1 elsewhere); 4 pi f / c [rad/m]."""
    noise = NoiseModel.for_sensor(SensorConfig(), CONFIG.frequencies_hz)
    w = 4 * np.pi * np.asarray(CONFIG.frequencies_hz) / noise.speed_of_light_m_per_s
    rng = np.random.default_rng(seed)
    clean = 0.0005 * (near_share * np.exp(1j * w * 10.0) + (1 - near_share) * np.exp(1j * w * 15.0))
    z_sigma = np.broadcast_to(noise.quadrature_sigma_v2(np.abs(clean)), (H, w.size))
    z = clean + z_sigma * (rng.standard_normal(z_sigma.shape) + 1j * rng.standard_normal(z_sigma.shape))
    grid = 7.0 + 0.001 * np.arange(6000)
    fit = np.abs(np.einsum("gf,kf->kg", np.exp(-1j * grid[:, None] * w[None, :]), z / z_sigma**2).real)
    depth = np.where(np.arange(W) < 8, 10.0, 15.0)[None].repeat(H, axis=0) + 0.03 * rng.standard_normal((H, W))
    depth[:, 8] = grid[np.argmax(fit, axis=1)]
    where = np.zeros((H, W), bool)
    where[BLOCK_REACH:H - BLOCK_REACH, 8] = True
    index = np.full((H, W), -1, np.intp)
    index[:, 8] = np.arange(H)
    return depth.astype(np.float32), z, z_sigma, where, index, w


def test_two_ranges__a_weak_far_return_is_found_with_its_neighbours_along_the_edge():
    """Sides 5 m apart at 10 m, the column 15 % far light: one pixel's phasors gain under 15 from a second return
    as often as not; the pixel and its two neighbours along the edge, alike, fitted together gain what
    chi-square(3) gives clean ones once in 10^4. Of the column's pixels more than 5 cm off the near side, pooled
    finds twice as many (35 of 56 in twenty columns, 17 alone)."""
    counts = np.zeros(3, int)
    for seed in range(20):
        depth, z, z_sigma, where, index, w = _column(0.85, seed)
        asked = np.abs(depth[where] - 10.0) > ranges.MIN_EDGE_M
        sigma = np.full(depth.shape, 0.03, np.float32)
        alone = ranges.two_ranges(depth, sigma, z[where[:, 8]], z_sigma[where[:, 8]], w, where)
        pooled = ranges.two_ranges(depth, sigma, z[where[:, 8]], z_sigma[where[:, 8]], w, where, (index, z, z_sigma))
        assert not (alone & ~pooled).any() and not (pooled & ~where).any()
        counts += [asked.sum(), alone[where][asked].sum(), pooled[where][asked].sum()]
    assert counts[0] >= 40 and counts[2] >= 0.55 * counts[0] and counts[1] <= 0.35 * counts[0]


def test_two_ranges__a_side_s_pixels_in_a_row_are_not_pooled_into_a_mixture():
    """A row of a side's own pixels 6 cm off its level (one return each at 10.06 m, between sides at 10 and 15 m):
    pooled with their neighbours along the edge they fit no mixture of the sides better than one return."""
    noise = NoiseModel.for_sensor(SensorConfig(), CONFIG.frequencies_hz)
    w = 4 * np.pi * np.asarray(CONFIG.frequencies_hz) / noise.speed_of_light_m_per_s
    for seed in range(10):
        rng = np.random.default_rng(seed)
        depth = np.where(np.arange(H) < EDGE_ROW, 10.0, 15.0)[:, None] + 0.03 * rng.standard_normal((H, W))
        z = np.broadcast_to(0.0007 * np.exp(1j * w * 10.06), (W, w.size))
        z_sigma = np.broadcast_to(noise.quadrature_sigma_v2(np.abs(z)), z.shape)
        z = z + z_sigma * (rng.standard_normal(z.shape) + 1j * rng.standard_normal(z.shape))
        depth[EDGE_ROW] = 10.06 + 0.03 * rng.standard_normal(W)
        where = np.zeros((H, W), bool)
        where[EDGE_ROW, BLOCK_REACH:W - BLOCK_REACH] = True
        index = np.full((H, W), -1, np.intp)
        index[EDGE_ROW] = np.arange(W)
        found = ranges.two_ranges(depth.astype(np.float32), np.full((H, W), 0.03, np.float32), z[where[EDGE_ROW]],
                                  z_sigma[where[EDGE_ROW]], w, where, (index, z, z_sigma))
        assert not found.any()
