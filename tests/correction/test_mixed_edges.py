"""The mixed-pixel stage at harder edges: two mixed pixels in a row (a diagonal edge seen with footprints wider than
the pixels' pitch), a dark plate far away whose few per cent of the light bias the depth by a few sigmas, and clean
surfaces far away, whose noisy steps must not look like an edge."""

from __future__ import annotations

import numpy as np
import pytest

from mpi_lidar.config import Config, SensorConfig
from mpi_lidar.correction.mixed import _stepped
from mpi_lidar.correction.options import Flag
from mpi_lidar.physics.noise import NoiseModel
from mpi_lidar.simulation.scenes import corner, flat_wall, render, scan_from_phasors
from tests.correction.mixed_stage import mixed_stage

pytestmark = pytest.mark.unit

CONFIG = Config()
H, W = 16, 16
EDGE_COLUMN = 6


def _scan(share, plate_m: float, plate_albedo: float, wall_m: float, wall_albedo: float, seed: int):
    """Each pixel's phasor: ``share`` (H, W) of the plate's return and the rest of the wall's."""
    freqs = np.asarray(CONFIG.frequencies_hz)
    w = 4 * np.pi * freqs / CONFIG.sensor.speed_of_light_m_per_s
    gamma = CONFIG.sensor.gamma_r_v2
    plate = gamma * plate_albedo / plate_m**2 * np.exp(1j * w * plate_m)
    wall = gamma * wall_albedo / wall_m**2 * np.exp(1j * w * wall_m)
    phasor = share[None] * plate[:, None, None] + (1 - share)[None] * wall[:, None, None]
    return scan_from_phasors("edge", phasor, CONFIG, np.random.default_rng(seed))


def _diagonal_share(footprint_px: float) -> np.ndarray:
    """The plate's share of each footprint (a box ``footprint_px`` pitches wide along the row) left of an edge
    running at 45 degrees, between pixel centres, on a grid H x (H + 8)."""
    y, x = np.mgrid[0:H, 0:H + 8].astype(float)
    edge = 3.5 + y
    return np.clip((edge - (x - footprint_px / 2)) / footprint_px, 0.0, 1.0)


@pytest.mark.parametrize("seed", [0, 1])
def test_find_mixed__a_diagonal_edge_with_two_mixed_pixels_in_a_row_is_flagged(seed):
    """Footprints two pitches wide: two or three pixels of each row hold both surfaces, equally bright 0.5 m apart
    at 5 m, so that no pixel's neighbour on either side is a flat side of its own."""
    share = _diagonal_share(2.0)
    mixed = (share > 0) & (share < 1)
    assert (mixed.sum(axis=1) >= 2).all()
    _, _, flags, _ = mixed_stage(_scan(share, 5.0, 0.5, 5.5, 0.5, seed))
    inner = mixed.copy()
    inner[:3] = inner[-3:] = False  # a side reaches three pixels out along a diagonal
    assert np.isin(flags[inner], [Flag.MIXED, Flag.TWO_RETURNS]).all()
    assert not np.isin(flags[~mixed], [Flag.MIXED, Flag.TWO_RETURNS]).any()


def test_stepped__two_pixels_between_two_flat_sides_and_not_a_ramp_or_a_kink():
    quiet = np.full((7, 10), 0.002, np.float32)
    two = np.tile(np.array([2.0, 2.0, 2.0, 2.0, 2.15, 2.35, 2.5, 2.5, 2.5, 2.5], np.float32), (7, 1))
    found = _stepped(two, quiet)
    assert found[:, [4, 5]].all() and found.sum() == 2 * two.shape[0]
    # a ramp of the same steps is a grazing surface; a flat side meeting a ramp, a corner's kink
    ramp = np.tile(2.0 + 0.15 * np.arange(10, dtype=np.float32), (7, 1))
    assert not _stepped(ramp, quiet).any()
    kink = np.tile(2.0 + 0.15 * np.maximum(np.arange(10, dtype=np.float32) - 3, 0), (7, 1))
    assert not _stepped(kink, quiet).any()
    # noise of 3 cm: the steps of 15-20 cm are under STEP_SIGMAS of it, or their sides not flat beyond it
    assert not _stepped(two, np.full(two.shape, 0.03, np.float32)).any()


def test_find_mixed__a_dark_plate_far_away_is_flagged_where_its_light_moves_the_depth():
    """A plate of albedo 0.05 at 5 m before a wall of 1.0 at 7 m: half the footprint holds 9 % of the light,
    which pulls the depth some 10 cm off the wall (3-4 of the wall's top-frequency sigmas, under the lone-edge
    tests' margins). Of that column's pixels more than 5 cm and 3 of their sigmas from both surfaces, in three
    scans, at least 90 % are flagged (half were before the step test read the fused depth); no surface pixel is."""
    share = np.where(np.arange(W) < EDGE_COLUMN, 1.0, 0.0)[None].repeat(H, axis=0)
    share[:, EDGE_COLUMN] = 0.5
    flagged = []
    for seed in range(3):
        scan = _scan(share, 5.0, 0.05, 7.0, 1.0, seed)
        _, _, flags, validity = mixed_stage(scan)
        noise = NoiseModel.for_sensor(SensorConfig(), scan.frequencies_hz)
        fused = noise.fuse(validity.scan.raw_pixels())
        depth, sigma = (values.reshape(H, W)[2:-2, EDGE_COLUMN] for values in (fused.depth_m, fused.sigma_m))
        off = np.minimum(np.abs(depth - 5.0), np.abs(depth - 7.0))
        flying = (off > 0.05) & (off > 3 * sigma)
        flagged.append(np.isin(flags[2:-2, EDGE_COLUMN][flying], [Flag.MIXED, Flag.TWO_RETURNS]))
        others = [c for c in range(W) if c != EDGE_COLUMN]
        assert not np.isin(flags[:, others], [Flag.MIXED, Flag.TWO_RETURNS]).any()
    every = np.concatenate(flagged)
    assert every.size >= 3 * H // 2 and every.mean() >= 0.9


@pytest.mark.parametrize(("scene", "distance_m"),
                         [(corner(90.0, 20.0, height=24, width=32, board_m=6.0, half_height_m=4.0), 20.0),
                          (flat_wall(45.0, 15.0, height=24, width=32), 15.0),
                          (flat_wall(60.0, 15.0, height=24, width=32), 15.0)])
def test_find_mixed__a_clean_wall_or_corner_far_away_is_left_as_the_gate_left_it(scene, distance_m):
    """At 15-20 m a pixel's depth is noisy by centimetres and a grazing wall steps by as much: no pixel is mixed,
    and the gate's decision comes back as it went in."""
    scan = render(scene, CONFIG, np.random.default_rng(3), patch_spacing_m=0.05 * distance_m)
    result, decision, flags, _ = mixed_stage(scan)
    assert not np.isin(flags, [Flag.MIXED, Flag.TWO_RETURNS]).any()
    assert result.decision is decision and result.mixed_pixels == result.resolved_pixels == 0
