"""The mixed-pixel stage's step test (:func:`stepped`): a pixel whose depth lies between two flat sides.

A footprint on both sides of a depth edge jumps twice, from the near side's depth to its own and on to the far
side's, wherever its depth falls between them (the mean of two equally bright returns included, which the
frequencies' agreement does not give away). A surface, however grazing or curved, changes its depth by similar
steps from pixel to pixel, and a corner's pixel has one flat side at most.

Each side's level is the median of a block of pixels (two along the direction, three across it), so its noise is
about half a pixel's and one pixel of the other side, where the edge runs diagonally, does not move it. The tests
weigh each quantity by its own noise: the two sides' levels must part by ``BLOCK_STEP_SIGMAS`` of theirs (the jump
a clean surface almost never shows), each side's slope, measured from the next block outwards, must stay below
``BLOCK_FLAT_SHARE`` of the step's mean slope between them beyond ``BLOCK_FLAT_SIGMAS`` of its noise (a grazing
surface's sides slope as steeply as the step), and the pixel must lie ``MIN_EDGE_M`` and ``BLOCK_PIXEL_SIGMAS``
of its own and the side's noise from each side: two sigmas of the pixel's own noise, as the sides, not the pixel,
carry the evidence of an edge. A second mixed pixel in a row is left to the one-line form of the test. A block
whose depths spread more than ``MAX_SPREAD`` times their noise (beyond the light's reach, where depths lie
anywhere, or across the edge) has no level; where they spread more than the noise model says, their spread is
their noise.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
from numpy.typing import NDArray

MIN_EDGE_M = 0.05  # the pixel lies this far from each side [m]...
BLOCK_PIXEL_SIGMAS = 2.0  # ...and this many sigmas of its own and the side's noise
BLOCK_STEP_SIGMAS = 5.0  # the sides' levels part by this many sigmas of their noise
BLOCK_FLAT_SHARE = 0.35  # a side's slope stays below this share of the step's mean slope between the sides [1]...
BLOCK_FLAT_SIGMAS = 1.0  # ...by this many sigmas of its noise
# A step's directions, each with the one across it along which a side's block is three pixels wide.
ACROSS = {(0, 1): (1, 0), (1, 0): (0, 1), (1, 1): (1, -1), (1, -1): (1, 1)}
BLOCK_ALONG = 2  # a side's block: this many pixels along the direction...
MIN_FINITE = 4  # ...of whose six at least this many have a finite depth
# The expected range of n normal draws less their lowest and highest, in sds, for n = 0..6 (inf for too few).
INNER_RANGE_SDS = np.array([np.inf, np.inf, np.inf, np.inf, 0.594, 0.990, 1.284])
MAX_SPREAD = 3.0  # a block's depths spread this many times their noise at most
BLOCK_REACH = 5  # a side's outer block reaches four pixels along a diagonal and one across it


class _Side(NamedTuple):
    """One side of some pixels (each (k,)): its level [m] and the level's noise [m], and its slope outwards [m per
    pixel] and the slope's noise [m per pixel]."""

    level: NDArray
    level_sigma: NDArray
    slope: NDArray
    slope_sigma: NDArray


def stepped(depth: NDArray, sigma: NDArray, where: NDArray | None = None) -> NDArray[np.bool_]:
    """Pixels (h, W) at a step between two flat sides (left and right, above and below, or diagonally) of
    ``depth`` (h, W) [m] with noise ``sigma`` (h, W) [m] (the module's docstring); only the pixels ``where``
    (h, W) is true are looked at (None: all), so that a band's few candidates cost what they are. A side's block
    that reaches past the band's border keeps its finite pixels, and none where fewer than ``MIN_FINITE`` remain."""
    h, w = depth.shape
    reach = BLOCK_REACH
    padded, noisy, ys, xs = padded_band(depth, sigma, where, reach, np.nan)
    own, own_sigma = padded[ys, xs], noisy[ys, xs]
    found = np.zeros(ys.size, bool)
    with np.errstate(invalid="ignore"):
        for (dy, dx), across in ACROSS.items():
            one, other = (_side(padded, noisy, ys, xs, (sign * dy, sign * dx), across) for sign in (1, -1))
            found |= _step(own, own_sigma, one, other)
    out = np.zeros((h, w), bool)
    out[ys[found] - reach, xs[found] - reach] = True
    return out


def padded_band(depth: NDArray, sigma: NDArray, where: NDArray | None, reach: int, sigma_fill: float
                ) -> tuple[NDArray, NDArray, NDArray[np.intp], NDArray[np.intp]]:
    """A band's depth (h, W) [m] and noise (h, W) [m] padded by ``reach`` pixels on every side (NaN depth, noise
    ``sigma_fill``), and the padded indices of the pixels ``where`` (h, W) is true (None: all)."""
    h, w = depth.shape
    ys, xs = np.nonzero(np.ones((h, w), bool) if where is None else where)
    padded = np.full((h + 2 * reach, w + 2 * reach), np.nan, dtype=np.float32)
    padded[reach:-reach, reach:-reach] = depth
    noisy = np.full((h + 2 * reach, w + 2 * reach), sigma_fill, dtype=np.float32)
    noisy[reach:-reach, reach:-reach] = sigma
    return padded, noisy, ys + reach, xs + reach


def _side(padded: NDArray, noisy: NDArray, ys: NDArray[np.intp], xs: NDArray[np.intp], along: tuple[int, int],
          across: tuple[int, int]) -> _Side:
    """The side of the pixels (``ys``, ``xs``) of ``padded`` depths [m] (``noisy`` their noise [m]) ``along`` a
    direction: its level is its first block's (``BLOCK_ALONG`` pixels from the neighbour on, three ``across``), its
    slope the next block's level less that, over the blocks' distance."""
    dy, dx = along
    (level, level_sigma), (outer, outer_sigma) = (
        block_level(padded, noisy, ys + k * dy, xs + k * dx, along, across) for k in (1, 1 + BLOCK_ALONG))
    return _Side(level, level_sigma, np.abs(outer - level) / BLOCK_ALONG,
                 np.hypot(level_sigma, outer_sigma) / BLOCK_ALONG)


def block_level(padded: NDArray, noisy: NDArray, ys: NDArray[np.intp], xs: NDArray[np.intp], along: tuple[int, int],
           across: tuple[int, int]) -> tuple[NDArray, NDArray]:
    """The median depth (k,) [m] of the block of ``BLOCK_ALONG`` pixels ``along`` from (``ys``, ``xs``) and one
    pixel either way ``across``, and its noise (k,) [m] (the median's share, sqrt(pi / 2n) of n values, of the
    pixels' mean noise or of their spread where larger); NaN where fewer than ``MIN_FINITE`` of its depths are
    finite or they spread beyond ``MAX_SPREAD`` times their noise."""
    (dy, dx), (ay, ax) = along, across
    at = [(ys + k * dy + j * ay, xs + k * dx + j * ax) for k in range(BLOCK_ALONG) for j in (-1, 0, 1)]
    values = np.stack([padded[a] for a in at])
    finite = np.isfinite(values)
    count = finite.sum(axis=0)
    ordered = np.sort(values, axis=0)  # NaN last: the finite ones' median lies at their middle index
    lower = np.take_along_axis(ordered, (np.maximum(count - 1, 0) // 2)[None], axis=0)[0]
    upper = np.take_along_axis(ordered, (count // 2)[None], axis=0)[0]
    sigma = np.where(finite, np.stack([noisy[a] for a in at]), 0.0).sum(axis=0) / np.maximum(count, 1)
    # The spread of the middle ones (one outlier either way left out) against what the noise gives: a block
    # beyond the light's reach (depths anywhere) or across the edge has no level.
    inner = (np.take_along_axis(ordered, np.maximum(count - 2, 0)[None], axis=0)[0] - ordered[1]) \
        / INNER_RANGE_SDS[np.minimum(count, len(INNER_RANGE_SDS) - 1)]
    usable = (count >= MIN_FINITE) & (inner <= MAX_SPREAD * sigma)
    spread = np.fmax(sigma, inner)  # where the noise model understates the spread, the spread
    return np.where(usable, (lower + upper) / 2, np.nan), np.sqrt(np.pi / 2 / np.maximum(count, 1)) * spread


def _step(own: NDArray, own_sigma: NDArray, one: _Side, other: _Side) -> NDArray[np.bool_]:
    """Whether pixels of depth ``own`` (k,) [m] and noise ``own_sigma`` (k,) [m] lie at a step between sides
    ``one`` and ``other``: the levels part by ``BLOCK_STEP_SIGMAS`` of their noise, each side's slope stays below
    ``BLOCK_FLAT_SHARE`` of the step's mean slope between the blocks' middles by ``BLOCK_FLAT_SIGMAS`` of its
    noise, and the pixel lies between them, ``MIN_EDGE_M`` and ``BLOCK_PIXEL_SIGMAS`` of the noise from each."""
    step = np.abs(one.level - other.level)
    significant = step > BLOCK_STEP_SIGMAS * np.hypot(one.level_sigma, other.level_sigma)
    slope_bound = BLOCK_FLAT_SHARE * step / (BLOCK_ALONG + 1)  # the blocks' middles lie this many pixels apart
    flat = ((one.slope + BLOCK_FLAT_SIGMAS * one.slope_sigma < slope_bound)
            & (other.slope + BLOCK_FLAT_SIGMAS * other.slope_sigma < slope_bound))
    apart = np.ones(own.shape, bool)
    for side in (one, other):
        margin = np.maximum(MIN_EDGE_M, BLOCK_PIXEL_SIGMAS * np.hypot(own_sigma, side.level_sigma))
        apart &= np.abs(side.level - own) > margin
    between = (one.level - own) * (own - other.level) > 0
    return np.asarray(significant & flat & apart & between)
