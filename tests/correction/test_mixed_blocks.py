"""The mixed-pixel stage's step test on blocks of pixels per side: a step of a few of a pixel's noise sigmas between
two flat sides is found, as long as each side's median level is precise; grazing planes, flat walls and sides beyond
the light's reach are not."""

from __future__ import annotations

import numpy as np
import pytest

from mpi_lidar.correction._mixed_steps import BLOCK_REACH, MAX_SPREAD, stepped
from mpi_lidar.correction.mixed import _stepped

pytestmark = pytest.mark.unit

H, W = 40, 40
EDGE = 20  # the mixed column
SIGMA_M = 0.025  # a pixel's noise at 10 m [m]


def _noisy(depth: np.ndarray, seed: int = 0) -> np.ndarray:
    return (depth + SIGMA_M * np.random.default_rng(seed).standard_normal(depth.shape)).astype(np.float32)


def _inside(found: np.ndarray) -> np.ndarray:
    return found[BLOCK_REACH:-BLOCK_REACH, BLOCK_REACH:-BLOCK_REACH]


def test_stepped__a_step_of_four_sigmas_between_precise_sides():
    """Sides 0.2 m apart (8 sigmas of a pixel), the mixed column at their mean: 4 sigmas from each, which the
    pixel's own noise alone does not make significant (the one-line test misses most), but the sides' blocks do."""
    columns = np.where(np.arange(W) < EDGE, 10.0, 10.2)
    columns[EDGE] = 10.1
    depth = _noisy(np.tile(columns, (H, 1)))
    sigma = np.full(depth.shape, SIGMA_M, np.float32)
    found = stepped(depth, sigma)
    rows = slice(BLOCK_REACH, H - BLOCK_REACH)
    assert found[rows, EDGE].mean() > 0.6
    others = np.delete(found[rows], EDGE, axis=1)
    assert not others.any(), "the sides' own pixels lie on their levels"
    assert _stepped(depth, sigma)[rows, EDGE].mean() < 0.5


@pytest.mark.parametrize("slope_sigmas", [1.0, 2.0, 3.0, 5.0])
def test_stepped__a_grazing_plane_is_not_a_step(slope_sigmas):
    """A plane whose depth climbs 1-5 noise sigmas a pixel: its sides slope as the step between them does."""
    plane = 10.0 + slope_sigmas * SIGMA_M * np.arange(W)[None, :] + 0.3 * SIGMA_M * np.arange(H)[:, None]
    for seed in range(3):
        depth = _noisy(np.broadcast_to(plane, (H, W)), seed)
        assert not _inside(stepped(depth, np.full(depth.shape, SIGMA_M, np.float32))).any()


def test_stepped__a_flat_wall_and_a_side_beyond_the_light_are_not_steps():
    """A flat wall beside pixels whose depths lie anywhere (no return, their noise understated tenfold): the
    noise region's blocks spread far beyond MAX_SPREAD times their noise, so they have no level."""
    depth = _noisy(np.full((H, W), 10.0))
    sigma = np.full(depth.shape, SIGMA_M, np.float32)
    assert not stepped(depth, sigma).any()
    rng = np.random.default_rng(5)
    depth[:, EDGE + 1:] = rng.uniform(0.0, 24.0, (H, W - EDGE - 1))
    sigma[:, EDGE + 1:] = 0.1 * 24.0 / np.sqrt(12)
    assert 24.0 / np.sqrt(12) > 2 * MAX_SPREAD * sigma[0, -1]
    assert not stepped(depth, sigma).any()


def test_stepped__only_the_pixels_asked_about():
    columns = np.where(np.arange(W) < EDGE, 2.0, 2.2)
    columns[EDGE] = 2.1
    depth = np.tile(columns, (H, 1)).astype(np.float32)
    quiet = np.full(depth.shape, 0.002, np.float32)
    only = np.zeros(depth.shape, bool)
    only[H // 2, EDGE] = True
    assert np.array_equal(stepped(depth, quiet, only), only)


def _rows_of(columns: np.ndarray, column_sigma: np.ndarray, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """Depths (H, W) whose columns are ``columns`` [m] with noise ``column_sigma`` [m], and that noise."""
    sigma = np.tile(column_sigma, (H, 1)).astype(np.float32)
    noise = sigma * np.random.default_rng(seed).standard_normal((H, W))
    return (np.tile(columns, (H, 1)) + noise).astype(np.float32), sigma


def test_stepped__a_run_of_three_mixed_pixels_between_precise_sides():
    """Footprints two pitches wide on a diagonal edge mix three pixels in a row (0.84, 0.44 and 0.09 of equal
    returns at 5 and 5.5 m): the block beside each holds the others, spreads across the edge and has no level; a
    side's block taken past the run has one, and the run's pixels lie in order between. No other pixel is found."""
    columns = np.where(np.arange(W) < EDGE, 5.0, 5.5)
    columns[EDGE:EDGE + 3] = (5.06, 5.25, 5.44)
    rows = slice(BLOCK_REACH, H - BLOCK_REACH)
    found = []
    for seed in range(3):
        depth, sigma = _rows_of(columns, np.full(W, 0.008), seed)
        flags = stepped(depth, sigma)
        found.append(flags[rows, EDGE:EDGE + 3])
        assert not np.delete(flags[rows], [EDGE, EDGE + 1, EDGE + 2], axis=1).any()
    assert np.concatenate(found).mean(axis=0).min() > 0.7


def test_stepped__a_side_too_noisy_to_be_shown_flat_stands_in_where_the_pixel_lies_far_off_it():
    """A dark side (a pixel's noise 12 cm) at 5 m beside a quiet one at 5.5 m, the mixed column at 5.4 m: the
    dark side's slope cannot be shown below the step's share, but the pixel lies far off its level and its surface
    carried back to the pixel, and three sigmas off the quiet side: most of the column is found (a quarter was
    before). A corner of a quiet flat side and a noisy sloping one is never found."""
    columns = np.where(np.arange(W) < EDGE, 5.0, 5.5)
    columns[EDGE] = 5.4
    column_sigma = np.where(np.arange(W) < EDGE, 0.12, 0.005)
    column_sigma[EDGE] = 0.03
    rows = slice(BLOCK_REACH, H - BLOCK_REACH)
    found = [stepped(*_rows_of(columns, column_sigma, seed))[rows, EDGE] for seed in range(3)]
    assert np.concatenate(found).mean() > 0.45
    x = np.arange(W)
    kink = np.where(x < EDGE, 5.0 + 0.08 * (EDGE - x), 5.0)
    for seed in range(10):
        assert not stepped(*_rows_of(kink, np.where(x < EDGE, 0.06, 0.005), seed))[rows].any()
