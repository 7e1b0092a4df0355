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
carry the evidence of an edge. Or its level along the edge does: a straight edge's mixed pixels lie in a line along
it, each holding about one mixture, so the median of the pixel and its two neighbours across the direction (along
the edge) has two thirds of a pixel's noise. Equal returns a few tenths of a metre apart far away mix to a depth a
few centimetres, two or three of a pixel's sigmas, from the nearer side, which the pixel alone often misses. The
three must be alike (within ``ALONG_SPREAD`` of their noise: a side's pixel beside the edge, whose neighbours across
lie on either side, has no level along it), both sides flat by ``ALONG_FLAT_SIGMAS`` of their slope's noise (a
grazing surface's noisy rows climb alike too), and the level or the pixel ``MIN_EDGE_M`` off each side.

A block whose depths spread more than ``MAX_SPREAD`` times their noise (beyond the light's reach, where depths lie
anywhere, or across the edge) has no level; where they spread more than the noise model says, their spread is their
noise.

Where an edge runs diagonally, or the footprint is wider than the pixels' pitch, two or three pixels in a row are
mixed, and the block beside a pixel holds some of them: its depths spread across the edge and it has no level.
There a side's block may begin up to ``MAX_START`` pixels out, the pixels between (the run's other mixed pixels)
lying in order between the pixel and that side's level, within ``ORDER_SIGMAS`` of their noise; the step's mean
slope is then taken over the blocks' middles' greater distance, and the pixel must lie ``RUN_PIXEL_SIGMAS`` from
each side (a side's own pixel beside a run has more chances to look stepped).

A dark side far away is too noisy for its flatness to be shown below the step's share. Such a side may stand in
for a flat one where the other side is flat, its slope is not significant (under ``HIDDEN_SLOPE_SIGMAS`` of its
noise), and the pixel lies ``HIDDEN_PIXEL_SIGMAS`` of its own, the level's and the unknown slope's noise (over the
distance to the block) from both its level and its surface carried back to the pixel along its measured slope (a
grazing or cornered side's pixel lies on that surface); the pixel then lies as many sigmas from the flat side.
"""

from __future__ import annotations

import itertools
from collections.abc import Iterable
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
MAX_START = 3  # a side's block begins at most this many pixels out, past a run of mixed pixels...
ORDER_SIGMAS = 2.0  # ...which lie in order between the pixel and the side, within this many sigmas of their noise
RUN_PIXEL_SIGMAS = 3.0  # ...and the pixel lies this many sigmas of its own and the side's noise from each side
HIDDEN_SLOPE_SIGMAS = 2.0  # a side not shown flat may stand in where its slope is within this many sigmas of 0...
HIDDEN_PIXEL_SIGMAS = 3.0  # ...and the pixel this many sigmas (its own, the level's, the slope's) off its level
# The median of three alike depths' sd over one's [1]: a pixel's level along the edge, where a straight edge's
# mixed pixels hold about one mixture, is known to this share of its noise.
ALONG_SIGMA_SHARE = 0.67
ALONG_SPREAD = 4.0  # ...where the three spread this many times their noise at most (1 % of alike ones spread more)
ALONG_FLAT_SIGMAS = 2.0  # ...and both sides are flat by this many sigmas of their slope's noise
# A side's outer block reaches MAX_START + 2 BLOCK_ALONG - 1 pixels along a diagonal, and one across it.
BLOCK_REACH = MAX_START + 2 * BLOCK_ALONG


class _Side(NamedTuple):
    """One side of some pixels (each (k,)): its level [m] and the level's noise [m], and its slope outwards [m per
    pixel] and the slope's noise [m per pixel]."""

    level: NDArray
    level_sigma: NDArray
    slope: NDArray
    slope_sigma: NDArray
    middle_px: float  # the level's block's middle lies this many pixels from the pixel
    drift: NDArray  # the slope with its sign: the depth's change per pixel outwards [m per pixel]


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
            blocks = {sign: _blocks(padded, noisy, ys, xs, (sign * dy, sign * dx), across, (1, 1 + BLOCK_ALONG))
                      for sign in (1, -1)}
            one, other = _side_of(blocks[1], 1), _side_of(blocks[-1], 1)
            along_edge = edge_level(padded, noisy, ys, xs, across)
            found |= _step(own, own_sigma, one, other, along_edge=along_edge)
            # Past a run of mixed pixels: only where a side's first block has no level and its first pixel a
            # depth (the run's next pixel), so that a clean surface's pixels, whose blocks have a level, and the
            # pixels beside no return, cost nothing more.
            again = np.flatnonzero(~found & ((np.isnan(one.level) & np.isfinite(padded[ys + dy, xs + dx]))
                                             | (np.isnan(other.level) & np.isfinite(padded[ys - dy, xs - dx]))))
            if again.size:
                known = {sign: {k: (level[again], sigma[again]) for k, (level, sigma) in by_start.items()}
                         for sign, by_start in blocks.items()}
                found[again] = _past_a_run(padded, noisy, ys[again], xs[again], (dy, dx), across, known,
                                           (along_edge[0][again], along_edge[1][again]))
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


def _past_a_run(padded: NDArray, noisy: NDArray, ys: NDArray[np.intp], xs: NDArray[np.intp],
                along: tuple[int, int], across: tuple[int, int], known: dict[int, dict[int, tuple[NDArray, NDArray]]],
                along_edge: tuple[NDArray, NDArray] | None = None) -> NDArray[np.bool_]:
    """Whether the pixels (``ys``, ``xs``) of ``padded`` depths [m] (``noisy`` their noise [m]) lie at a step
    whose sides' blocks begin 1 to ``MAX_START`` pixels out either way ``along`` a direction, at least one beyond
    the neighbour, the pixels between lying in order between the pixel and the side (:func:`_in_order`).
    ``known``: per side (1 along, -1 against) the blocks' levels already taken, by how far out they begin;
    ``along_edge``: the pixels' level along the edge and its noise (:func:`edge_level`; None: not used)."""
    dy, dx = along
    own, own_sigma = padded[ys, xs], noisy[ys, xs]
    offsets = range(1, MAX_START + BLOCK_ALONG + 1)
    blocks = {sign: known[sign] | _blocks(padded, noisy, ys, xs, (sign * dy, sign * dx), across,
                                          [k for k in offsets if k not in known[sign]]) for sign in (1, -1)}
    sides = {(sign, start): _side_of(blocks[sign], start) for sign in (1, -1) for start in range(1, MAX_START + 1)}
    found = np.zeros(ys.size, bool)
    for first in range(1, MAX_START + 1):
        for second in range(1, MAX_START + 2 - first):
            if first == second == 1:
                continue
            one, other = sides[1, first], sides[-1, second]
            ordered = (_in_order(padded, noisy, ys, xs, (dy, dx), first, one.level, one.level_sigma)
                       & _in_order(padded, noisy, ys, xs, (-dy, -dx), second, other.level, other.level_sigma))
            found |= ordered & _step(own, own_sigma, one, other, first + second + BLOCK_ALONG - 1, RUN_PIXEL_SIGMAS,
                                     along_edge)
    return found


def _in_order(padded: NDArray, noisy: NDArray, ys: NDArray[np.intp], xs: NDArray[np.intp], along: tuple[int, int],
              start: int, level: NDArray, level_sigma: NDArray) -> NDArray[np.bool_]:
    """Whether the depths from the pixels (``ys``, ``xs``) ``along`` a direction up to ``start`` - 1 pixels out,
    then the side's ``level`` (k,) [m] (noise ``level_sigma`` [m]), change one way (each from the one before by
    no less than -``ORDER_SIGMAS`` of the two's noise): a run of mixed pixels between the pixel and the side."""
    dy, dx = along
    chain = [(padded[ys + k * dy, xs + k * dx], noisy[ys + k * dy, xs + k * dx]) for k in range(start)]
    chain.append((level, level_sigma))
    way = np.sign(level - chain[0][0])
    ordered = np.ones(ys.size, bool)
    for (before, before_sigma), (after, after_sigma) in itertools.pairwise(chain):
        ordered &= way * (after - before) > -ORDER_SIGMAS * np.hypot(before_sigma, after_sigma)
    return ordered


def _blocks(padded: NDArray, noisy: NDArray, ys: NDArray[np.intp], xs: NDArray[np.intp], along: tuple[int, int],
            across: tuple[int, int], starts: Iterable[int]) -> dict[int, tuple[NDArray, NDArray]]:
    """The levels (k,) [m] and their noise (k,) [m] (:func:`block_level`) of the blocks ``along`` a direction
    from the pixels (``ys``, ``xs``) of ``padded`` depths [m] (``noisy`` their noise [m]), by how many pixels out
    each begins (``starts``)."""
    dy, dx = along
    return {k: block_level(padded, noisy, ys + k * dy, xs + k * dx, along, across) for k in starts}


def _side(padded: NDArray, noisy: NDArray, ys: NDArray[np.intp], xs: NDArray[np.intp], along: tuple[int, int],
          across: tuple[int, int], start: int = 1) -> _Side:
    """The side of the pixels (``ys``, ``xs``) of ``padded`` depths [m] (``noisy`` their noise [m]) ``along`` a
    direction: its level is its first block's (``BLOCK_ALONG`` pixels from ``start`` pixels out on, three
    ``across``), its slope the next block's level less that, over the blocks' distance."""
    return _side_of(_blocks(padded, noisy, ys, xs, along, across, (start, start + BLOCK_ALONG)), start)


def _side_of(blocks: dict[int, tuple[NDArray, NDArray]], start: int) -> _Side:
    """The side whose first block begins ``start`` pixels out, of ``blocks``' levels (:func:`_blocks`)."""
    (level, level_sigma), (outer, outer_sigma) = blocks[start], blocks[start + BLOCK_ALONG]
    return _Side(level, level_sigma, np.abs(outer - level) / BLOCK_ALONG,
                 np.hypot(level_sigma, outer_sigma) / BLOCK_ALONG, start + (BLOCK_ALONG - 1) / 2,
                 (outer - level) / BLOCK_ALONG)


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


def _hidden(own: NDArray, own_sigma: NDArray, side: _Side) -> NDArray[np.bool_]:
    """Whether a side too noisy to be shown flat may stand in for a flat one: its slope is not significant, and
    the pixels of depth ``own`` (k,) [m] (noise ``own_sigma`` [m]) lie ``HIDDEN_PIXEL_SIGMAS`` of their own, the
    level's and the slope's noise over the distance to the block from both its level and its surface carried back
    to them along its slope (a grazing side's pixel lies on that surface)."""
    margin = np.maximum(MIN_EDGE_M, HIDDEN_PIXEL_SIGMAS * np.sqrt(
        own_sigma**2 + side.level_sigma**2 + (side.middle_px * side.slope_sigma) ** 2))
    carried = side.level - side.middle_px * side.drift
    return np.asarray((side.slope < HIDDEN_SLOPE_SIGMAS * side.slope_sigma) & (np.abs(side.level - own) > margin)
                      & (np.abs(carried - own) > margin))


def _step(own: NDArray, own_sigma: NDArray, one: _Side, other: _Side, apart_px: int = BLOCK_ALONG + 1,
          pixel_sigmas: float = BLOCK_PIXEL_SIGMAS, along_edge: tuple[NDArray, NDArray] | None = None,
          ) -> NDArray[np.bool_]:
    """Whether pixels of depth ``own`` (k,) [m] and noise ``own_sigma`` (k,) [m] lie at a step between sides
    ``one`` and ``other``: the levels part by ``BLOCK_STEP_SIGMAS`` of their noise, each side's slope stays below
    ``BLOCK_FLAT_SHARE`` of the step's mean slope between the blocks' middles (``apart_px`` pixels apart) by
    ``BLOCK_FLAT_SIGMAS`` of its noise, and the pixel lies between them, ``MIN_EDGE_M`` and ``pixel_sigmas`` of
    the noise from each, or its level along the edge does (``along_edge``: its depth (k,) [m] and noise (k,) [m],
    :func:`edge_level`; None: not asked), itself lying between them."""
    step = np.abs(one.level - other.level)
    significant = step > BLOCK_STEP_SIGMAS * np.hypot(one.level_sigma, other.level_sigma)
    slope_bound = BLOCK_FLAT_SHARE * step / apart_px
    quiet = [side.slope + BLOCK_FLAT_SIGMAS * side.slope_sigma < slope_bound for side in (one, other)]
    hidden = [_hidden(own, own_sigma, side) for side in (one, other)]
    both_quiet = quiet[0] & quiet[1]
    flat = both_quiet | (quiet[0] & hidden[1]) | (hidden[0] & quiet[1])
    # Where a side stands in so, the pixel lies as far from the quiet side too: the noisy side's evidence is less.
    sigmas = np.where(both_quiet, pixel_sigmas, max(pixel_sigmas, HIDDEN_PIXEL_SIGMAS))
    between = (one.level - own) * (own - other.level) > 0
    apart = np.ones(own.shape, bool)
    for side in (one, other):
        apart &= np.abs(side.level - own) > np.maximum(MIN_EDGE_M, sigmas * np.hypot(own_sigma, side.level_sigma))
    if along_edge is not None:  # or its level along the edge does, itself or the pixel MIN_EDGE_M off
        level, level_sigma = along_edge
        firm = [side.slope + ALONG_FLAT_SIGMAS * side.slope_sigma < slope_bound for side in (one, other)]
        along = firm[0] & firm[1] & ((one.level - level) * (level - other.level) > 0)
        for side in (one, other):
            off = np.abs(side.level - level)
            along &= (off > sigmas * np.hypot(level_sigma, side.level_sigma)) \
                & (np.fmax(off, np.abs(side.level - own)) > MIN_EDGE_M)
        apart |= along
    return np.asarray(significant & flat & apart & between)


def edge_level(padded: NDArray, noisy: NDArray, ys: NDArray[np.intp], xs: NDArray[np.intp],
               across: tuple[int, int]) -> tuple[NDArray, NDArray]:
    """The pixels' level along the edge: the median (k,) [m] of the depths at (``ys``, ``xs``) of ``padded`` and
    one pixel either way ``across`` the step (along the edge, where its mixed pixels hold about one mixture), and
    its noise (k,) [m], ``ALONG_SIGMA_SHARE`` of the three's mean (``noisy``); NaN where any is not finite or the
    three are not alike, spreading more than ``ALONG_SPREAD`` times their mean noise (a side's pixel beside the
    edge, whose neighbours across lie on either side of it, has no level along it)."""
    dy, dx = across
    at = [(ys - dy, xs - dx), (ys, xs), (ys + dy, xs + dx)]
    three = np.stack([padded[a] for a in at])
    sigma = np.stack([noisy[a] for a in at]).mean(axis=0)
    alike = three.max(axis=0) - three.min(axis=0) <= ALONG_SPREAD * sigma
    return np.where(alike, np.median(three, axis=0), np.nan), ALONG_SIGMA_SHARE * sigma
