"""The mixed-pixel stage's two-range test: a pixel whose phasors are two returns at its sides' ranges, metres apart,
is found even where its frequencies agree (their mixtures wrap to about one depth) and its depth lies within its own
noise of a side; a side's own pixel, one return at its range, and a grazing surface's, one return between its
sides, are not."""

from __future__ import annotations

import numpy as np
import pytest

from mpi_lidar.config import Config, SensorConfig
from mpi_lidar.correction import _mixed_ranges as ranges
from mpi_lidar.correction._mixed_steps import BLOCK_REACH
from mpi_lidar.correction.gating import GateDecision
from mpi_lidar.correction.mixed import MARGIN_ROWS, find_mixed
from mpi_lidar.correction.options import CorrectionOptions, Flag
from mpi_lidar.correction.tiles import scan_tiles
from mpi_lidar.correction.validity import check_validity
from mpi_lidar.physics.noise import NoiseModel
from mpi_lidar.simulation.scenes import scan_from_phasors

pytestmark = pytest.mark.unit

CONFIG = Config()
NOISE = NoiseModel.for_sensor(SensorConfig(), CONFIG.frequencies_hz)
FREQS = np.asarray(CONFIG.frequencies_hz)
W_RAD_PER_M = 4 * np.pi * FREQS / NOISE.speed_of_light_m_per_s
H, W = 16, 16
EDGE = 8  # the column asked about
NEAR_M, FAR_M = 10.0, 15.0
AMPLITUDE_V2 = 0.0007  # the two returns' amplitude [V^2]: the highest frequency's depth noise about 4.7 cm
SIDE_SIGMA_M = 0.03  # the sides' pixels' noise [m]


def _phasors(near_share: np.ndarray, rng: np.random.Generator, near_m: float = NEAR_M,
             far_m: float = FAR_M) -> tuple[np.ndarray, np.ndarray]:
    """Phasors (k, F) of ``near_share`` (k,) of the light at ``near_m`` and the rest at ``far_m``, with the sensor
    model's quadrature noise, and that noise (k, F)."""
    z = AMPLITUDE_V2 * (near_share[:, None] * np.exp(1j * W_RAD_PER_M * near_m)
                        + (1 - near_share[:, None]) * np.exp(1j * W_RAD_PER_M * far_m))
    sigma = NOISE.quadrature_sigma_v2(np.abs(z))
    noisy = z + sigma * (rng.standard_normal(z.shape) + 1j * rng.standard_normal(z.shape))
    return noisy, sigma


def _single_range_m(z: np.ndarray, sigma: np.ndarray, about_m: float) -> np.ndarray:
    """The range (k,) [m] within 3 m of ``about_m`` of the one return that best fits phasors ``z`` (k, F) of noise
    ``sigma`` (k, F): what the fused depth of the pixel's frequencies estimates."""
    grid = about_m + np.arange(-3.0, 3.0, 0.001)
    basis = np.exp(1j * grid[:, None] * W_RAD_PER_M[None, :])  # (G, F)
    fit = np.abs(np.einsum("gf,kf->kg", basis.conj(), z / sigma**2).real) ** 2
    return np.asarray(grid[np.argmax(fit, axis=1)])


def _depth_map(rng: np.random.Generator, own_m: float | np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Fused depths (H, W): the near side left of EDGE, the far side right, ``own_m`` in column EDGE; their noise;
    and the pixels asked about (column EDGE, away from the border)."""
    depth = np.where(np.arange(W) < EDGE, NEAR_M, FAR_M)[None].repeat(H, axis=0).astype(np.float64)
    depth += SIDE_SIGMA_M * rng.standard_normal(depth.shape)
    where = np.zeros(depth.shape, bool)
    where[BLOCK_REACH:H - BLOCK_REACH, EDGE] = True
    depth[:, EDGE] = NEAR_M
    depth[where] = own_m
    sigma = np.full(depth.shape, SIDE_SIGMA_M)
    return depth.astype(np.float32), sigma.astype(np.float32), where


def _found(near_share: float, seed: int, near_m: float = NEAR_M, far_m: float = FAR_M) -> tuple[np.ndarray, ...]:
    """Whether each pixel of column EDGE, ``near_share`` of its light at ``near_m`` and the rest at ``far_m``, is
    found between the sides at 10 and 15 m, and its depth (the best single range)."""
    rng = np.random.default_rng(seed)
    k = H - 2 * BLOCK_REACH
    z, z_sigma = _phasors(np.full(k, near_share), rng, near_m, far_m)
    own = _single_range_m(z, z_sigma, near_m)
    depth, sigma, where = _depth_map(rng, own)
    return ranges.two_ranges(depth, sigma, z, z_sigma, W_RAD_PER_M, where)[where], own


def test_two_ranges__a_mixture_of_its_sides_ranges_is_found_where_its_depth_lies_near_a_side():
    """Three quarters of the light at 10 m, a quarter at 15 m: each frequency's mixture wraps to within a few
    centimetres of 10 m, the depth within the 5 cm margin of the step tests' two sigmas; the mixture's pattern over
    the frequencies gives it away."""
    found, own = (np.concatenate(parts) for parts in zip(*(_found(0.75, seed) for seed in range(8)), strict=True))
    asked = np.abs(own - NEAR_M) > ranges.MIN_EDGE_M
    assert asked.sum() >= 8 and np.abs(own - NEAR_M).max() < 0.3  # near the near side, metres from the far
    assert found[asked].mean() > 0.9


def test_two_ranges__one_return_at_a_side_or_between_the_sides_is_not_a_mixture():
    """A side's own pixel 6 cm off its level (one return at 10.06 m), and a grazing surface's (one return at
    12.5 m, between the sides): neither fits two returns at the sides' ranges better than one."""
    at_side = np.concatenate([_found(1.0, seed, NEAR_M + 0.06)[0] for seed in range(20)])
    between = np.concatenate([_found(1.0, seed, 12.5, 12.5)[0] for seed in range(20)])
    assert not at_side.any() and not between.any()


def test_two_ranges__sides_under_a_metre_apart_or_a_depth_on_a_side_are_not_asked():
    """The sides 0.5 m apart (their phasors part by under MIN_GAP_M's 0.26 rad), or the pixel's depth within
    MIN_EDGE_M of a side: not looked at, however mixed."""
    assert ranges.MIN_GAP_M > 0.5
    rng = np.random.default_rng(0)
    k = H - 2 * BLOCK_REACH
    depth, sigma, where = _depth_map(rng, NEAR_M + 0.2)
    depth[:, EDGE + 1:] = NEAR_M + 0.5
    z, z_sigma = _phasors(np.full(k, 0.5), rng, NEAR_M, NEAR_M + 0.5)
    assert not ranges.two_ranges(depth, sigma, z, z_sigma, W_RAD_PER_M, where).any()
    depth, sigma, where = _depth_map(rng, NEAR_M + 0.01)
    z, z_sigma = _phasors(np.full(k, 0.75), rng)
    assert not ranges.two_ranges(depth, sigma, z, z_sigma, W_RAD_PER_M, where).any()


def _edge_scan(seed: int):
    """A plate (albedo 0.5) at 10 m left of column EDGE, a wall (0.5) at 15 m right of it, and three quarters of
    column EDGE's footprint on the plate, on a grid H x W through the sensor model."""
    share = np.where(np.arange(W) < EDGE, 1.0, 0.0)[None].repeat(H, axis=0)
    share[:, EDGE] = 0.75
    gamma = CONFIG.sensor.gamma_r_v2
    plate = gamma * 0.5 / NEAR_M**2 * np.exp(1j * W_RAD_PER_M * NEAR_M)
    wall = gamma * 0.5 / FAR_M**2 * np.exp(1j * W_RAD_PER_M * FAR_M)
    phasor = share[None] * plate[:, None, None] + (1 - share)[None] * wall[:, None, None]
    return scan_from_phasors("edge", phasor, CONFIG, np.random.default_rng(seed))


def test_find_mixed__the_same_pixels_whether_read_in_tiles_of_three_rows_or_at_once():
    """The stage reads each tile with MARGIN_ROWS rows either side, as far as a side's block taken past a run of
    mixed pixels reaches: the two-range and the step tests give every pixel what the whole scan gives it."""
    assert MARGIN_ROWS >= BLOCK_REACH
    for seed in range(2):
        scan = _edge_scan(seed)
        flags = []
        for rows in (H, 3):
            tiles = scan_tiles(scan, rows * W)
            validity = check_validity(scan, NOISE, CorrectionOptions(), tiles)
            decision = GateDecision(np.where(validity.flags == Flag.NOT_NEEDED, np.uint8(Flag.NO_MULTIPATH),
                                             validity.flags).astype(np.uint8), 0, served=True)
            flags.append(find_mixed(validity.scan, tiles, validity, decision, NOISE).decision.flags)
        assert np.array_equal(flags[0], flags[1])
        column = flags[0].reshape(H, W)[:, EDGE]
        assert np.isin(column, [Flag.MIXED, Flag.TWO_RETURNS]).any()
