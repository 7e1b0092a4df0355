"""The mixed-pixel stage's one-sided test (:func:`lost_light`): a pixel beside a surface with no usable return.

Where one side of a depth edge returns too little light to range (a dark plate far away, or a dark wall behind a
bright plate), the step tests have one side only, and the frequencies' agreement tells nothing at gaps under a
metre. What is left is the lit side: a pixel whose footprint lies partly on the dark surface receives less of the
lit side's light, and its depth is pulled towards the dark surface's by that surface's share of the light, which
the pixel's own noise, larger by as much as its light is less, spreads further. Such a pixel is MIXED where

- a neighbour has no usable return (NO_RETURN), and the side opposite it is lit: a block of six pixels
  (:func:`mpi_lidar.correction._mixed_steps.block_level`, two along the direction and three across), its level
  extrapolated to the pixel from the next block outwards, so that a grazing surface's slope does not count;
- the pixel's summed amplitude lies between the lit block's and the dark side's block's, at least ``MIN_LOSS`` of
  the step between them from each and ``LOSS_SIGMAS`` of their noise: its footprint lost light to something beside
  the lit surface and holds more than the dark side gives (a pixel of a dim surface that passed the validity test
  by its noise, where a corner's grazing face mostly returns too little, has the dark side's light);
- its depth may lie ``MIN_EDGE_M`` from that level, within ``LEVEL_SIGMAS`` of the level's noise, and lies at
  least ``MIN_OFF_M`` from it. Its own noise does not widen the margin: a pixel that lost most of the light is as
  noisy as the 5 cm it may be off.

Which way the depth moved is not known (the dark side's depth is not), so the test is two-sided. A pixel at a
silhouette against nothing (the sky) loses light the same way but keeps its depth: it is withheld only where its
noise, not a mixture, moves its depth as far.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from mpi_lidar.correction import _mixed_steps as _blocks

MIN_EDGE_M = 0.05  # the pixel's depth may lie this far from the lit side's [m]...
LEVEL_SIGMAS = 1.0  # ...within this many sigmas of the side's level...
MIN_OFF_M = 0.025  # ...and lies at least this far from it [m]
SLOPE_SIGMAS = 2.0  # a lit side slopes where its two blocks' levels part by this many sigmas of their noise
MIN_LOSS = 0.2  # the pixel's amplitude lies this share of the step between the sides' from each [1]...
LOSS_SIGMAS = 3.0  # ...by this many sigmas of their noise
DIRECTIONS = tuple((dy, dx) for dy in (-1, 0, 1) for dx in (-1, 0, 1) if dy or dx)
BLOCK_MIDDLE = (_blocks.BLOCK_ALONG + 1) / 2  # a block's middle lies this many pixels along from the pixel
DARK_REACH = 1 + 2 * _blocks.BLOCK_ALONG  # the outer block reaches this many pixels along a diagonal, one across


def beside_no_return(no_return: NDArray[np.bool_]) -> NDArray[np.bool_]:
    """Pixels (h, W) with a neighbour within one pixel that has no usable return (``no_return`` (h, W))."""
    h, w = no_return.shape
    padded = np.zeros((h + 2, w + 2), bool)
    padded[1:-1, 1:-1] = no_return
    out = np.zeros((h, w), bool)
    for dy, dx in DIRECTIONS:
        out |= padded[1 + dy:h + 1 + dy, 1 + dx:w + 1 + dx]
    return out


def lost_light(depth: NDArray, sigma: NDArray, amplitude: NDArray, amplitude_sigma: NDArray,
               no_return: NDArray[np.bool_], where: NDArray[np.bool_]) -> NDArray[np.bool_]:
    """Pixels (h, W) among ``where`` (h, W) beside a neighbour with no usable return (``no_return`` (h, W)) whose
    amplitude lost light against the lit side opposite it and whose depth lies off that side's (the module's
    docstring). ``depth`` (h, W) [m] and ``sigma`` (h, W) [m]: the fused depth (NaN where not measured) and its
    noise; ``amplitude`` (h, W) [V^2] and ``amplitude_sigma`` (h, W) [V^2]: the frequencies' summed amplitude and
    its noise. Pixels whose blocks reach past the band's border keep the finite pixels there."""
    h, w = depth.shape
    ys, xs = np.nonzero(where)
    reach = DARK_REACH
    padded, noisy, bright, bright_noise = (_padded(values, reach) for values in
                                           (depth, sigma, amplitude, amplitude_sigma))
    dark = np.zeros((h + 2 * reach, w + 2 * reach), bool)
    dark[reach:-reach, reach:-reach] = no_return
    ys, xs = ys + reach, xs + reach
    own, light, light_sigma = padded[ys, xs], bright[ys, xs], bright_noise[ys, xs]
    found = np.zeros(ys.size, bool)
    with np.errstate(invalid="ignore"):
        for dy, dx in DIRECTIONS:
            facing = dark[ys - dy, xs - dx]
            if not facing.any():
                continue
            across = (dx, -dy) if dy and dx else (abs(dx), abs(dy))
            level, level_sigma = _extrapolated(padded, noisy, ys, xs, (dy, dx), across)
            lit, lit_sigma = _blocks.block_level(bright, bright_noise, ys + dy, xs + dx, (dy, dx), across)
            unlit, unlit_sigma = _blocks.block_level(bright, bright_noise, ys - dy, xs - dx, (-dy, -dx), across)
            scattered = ~np.isfinite(unlit)  # amplitudes scattered beyond their noise: no light to speak of
            unlit, unlit_sigma = np.where(scattered, 0.0, unlit), np.where(scattered, 0.0, unlit_sigma)
            lost = ((light - unlit < (1 - MIN_LOSS) * (lit - unlit))
                    & (lit - light > LOSS_SIGMAS * np.hypot(light_sigma, lit_sigma))
                    & (light - unlit > MIN_LOSS * (lit - unlit))
                    & (light - unlit > LOSS_SIGMAS * np.hypot(light_sigma, unlit_sigma)))
            margin = np.maximum(MIN_EDGE_M - LEVEL_SIGMAS * level_sigma, MIN_OFF_M)
            found |= facing & lost & (np.abs(own - level) > margin)
    out = np.zeros((h, w), bool)
    out[ys[found] - reach, xs[found] - reach] = True
    return out


def _padded(values: NDArray, reach: int) -> NDArray:
    """``values`` (h, W) with ``reach`` NaN pixels on every side."""
    out = np.full((values.shape[0] + 2 * reach, values.shape[1] + 2 * reach), np.nan, dtype=np.float64)
    out[reach:-reach, reach:-reach] = values
    return out


def _extrapolated(padded: NDArray, noisy: NDArray, ys: NDArray[np.intp], xs: NDArray[np.intp],
                  along: tuple[int, int], across: tuple[int, int]) -> tuple[NDArray, NDArray]:
    """The lit side's depth (k,) [m] at the pixels (``ys``, ``xs``): the level of its first block (from the
    neighbour ``along`` on) carried back to the pixel along the line through the next block's, and its noise
    (k,) [m]; NaN where either block has no level."""
    dy, dx = along
    (near, near_sigma), (outer, outer_sigma) = (
        _blocks.block_level(padded, noisy, ys + k * dy, xs + k * dx, along, across)
        for k in (1, 1 + _blocks.BLOCK_ALONG))
    back = BLOCK_MIDDLE / _blocks.BLOCK_ALONG  # the pixel lies this many blocks' spacings before the first
    sloped = np.abs(outer - near) > SLOPE_SIGMAS * np.hypot(near_sigma, outer_sigma)
    return (np.where(sloped, near - back * (outer - near), near),
            np.where(sloped, np.hypot((1 + back) * near_sigma, back * outer_sigma), near_sigma))
