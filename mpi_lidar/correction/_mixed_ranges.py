"""The mixed-pixel stage's two-range test (:func:`two_ranges`): a pixel whose phasors are two returns at its sides'.

Far away, a pixel on a depth edge a few metres deep escapes the other tests: the frequencies' phases turn apart by
about 0.26 rad per metre of gap at the 6.25 MHz spacing, so at some gaps each frequency's mixture lies near the
same depth (their disagreement wraps and looks consistent), a free two-return fit of four noisy phasors is loose,
and its depth lies within its own noise of a side, which the step tests need it to leave by two of its sigmas.
What the pixel still holds is the mixture's pattern over the frequencies, and the neighbourhood tells where its two
returns lie: at the ranges of the surfaces either side. With those ranges fixed, the returns' amplitudes follow
from the phasors linearly, and the test is a regular one of one parameter more than a single return:

- the two sides (left and right, above and below, or diagonally) have levels (the median of a block of six
  pixels, :func:`mpi_lidar.correction._mixed_steps.block_level`) at least ``MIN_GAP_M`` apart and
  ``STEP_SIGMAS`` of their noise; their flatness is not asked for, as a dark side's noise cannot show it, and a
  grazing or curved surface's pixel, a single return between its sides, fits no mixture of them;
- the pixel's fused depth lies ``MIN_EDGE_M`` from the nearer side's level (a flying point, not a side's pixel);
- its phasors, over the frequencies' gains, fit two returns at the sides' ranges (each within one sigma of its
  level; amplitudes not negative, the weaker at least ``MIN_SHARE`` of the light) within chi-square's
  1 - ``FIT_P_VALUE`` quantile, and better than one return at the pixel's own depth (within one of its sigmas) by
  ``DELTA_CHI2``: the chance a clean pixel, one return at one side's range, gains that much from a second
  amplitude is chi-square(1)'s beyond it.

Where the far return is weak (a few tenths of the light) one pixel's gain is often under ``DELTA_CHI2``. Along a
straight edge its neighbours hold about the same mixture: where the pixel and its two neighbours across the step
(along the edge) are alike in depth (:func:`mpi_lidar.correction._mixed_steps.edge_level`), the three are
fitted together, two returns at the same sides' ranges against one return each, and gain ``POOLED_DELTA_CHI2``
(three amplitudes more: chi-square(3)'s same tail) with the sum of their mixtures' chi-squares within
``FIT_P_VALUE``.
"""

from __future__ import annotations

import itertools

import numpy as np
from numpy.typing import NDArray

from mpi_lidar.correction import _mixed_steps as _blocks

MIN_GAP_M = 1.0  # the sides' levels lie this far apart [m]: nearer, their phasors part by under 0.26 rad...
STEP_SIGMAS = 5.0  # ...and this many sigmas of their noise
MIN_EDGE_M = 0.05  # the pixel's depth lies this far from the nearer side's level [m]
# Two returns at the sides' ranges fit better than one at the pixel's depth by this much [1]: chi-square(1)'s
# 1 - 1e-4 quantile, the second amplitude being the one parameter more.
DELTA_CHI2 = 15.0
FIT_P_VALUE = 1e-3  # ...and fit within chi-square's 1 - this quantile (2F - 2 degrees of freedom)
MIN_SHARE = 0.05  # ...the weaker of them holding this share of the light at least [1]
# A pixel and its two neighbours along the edge, alike, fitted together: chi-square(3)'s 1 - 1e-4 quantile [1].
POOLED_DELTA_CHI2 = 21.1
LEVEL_STEPS = (-1.0, 0.0, 1.0)  # each side's range: its level and one sigma either way [sigmas]
OWN_STEPS = (-1.0, -0.5, 0.0, 0.5, 1.0)  # the single return's range about the pixel's depth [sigmas]


def two_ranges(depth: NDArray, sigma: NDArray, phasors: NDArray, phasor_sigma: NDArray, w: NDArray,
               where: NDArray[np.bool_], around: tuple[NDArray, NDArray, NDArray] | None = None,
               ) -> NDArray[np.bool_]:
    """Pixels (h, W) among ``where`` (h, W) whose phasors are two returns at their sides' ranges (the module's
    docstring). ``depth`` (h, W) [m] and ``sigma`` (h, W) [m]: the fused depth (NaN where not measured) and its
    noise; ``phasors`` (k, F) [V^2] and ``phasor_sigma`` (k, F) [V^2]: the pixels ``where``'s (in ``np.nonzero``
    order) phasors over the frequencies' gains and their quadrature noise so scaled; ``w`` (F,): 4 pi f / c
    [rad/m]. ``around``: each pixel's row (h, W) in the phasors (n, F) [V^2] and their noise (n, F) [V^2] of the
    pixels a pixel may pool with along the edge (-1: none; None: no pooling). Pixels whose blocks reach past the
    band's border keep the finite pixels there."""
    h, w_ = depth.shape
    reach = _blocks.BLOCK_REACH
    padded, noisy, ys, xs = _blocks.padded_band(depth, sigma, where, reach, np.nan)
    own, own_sigma = padded[ys, xs].astype(np.float64), noisy[ys, xs].astype(np.float64)
    weighted = phasors / phasor_sigma
    found = np.zeros(ys.size, bool)
    with np.errstate(invalid="ignore"):
        for along, across in _blocks.ACROSS.items():
            one, other = (_blocks.block_level(padded, noisy, ys + sign * along[0], xs + sign * along[1],
                                              (sign * along[0], sign * along[1]), across) for sign in (1, -1))
            levels = (one[0].astype(np.float64), other[0].astype(np.float64))
            level_sigmas = (one[1].astype(np.float64), other[1].astype(np.float64))
            step = np.abs(levels[0] - levels[1])
            nearer = np.minimum(np.abs(own - levels[0]), np.abs(own - levels[1]))
            asked = np.flatnonzero(~found & (step >= MIN_GAP_M)
                                   & (step > STEP_SIGMAS * np.hypot(level_sigmas[0], level_sigmas[1]))
                                   & (nearer > MIN_EDGE_M))
            if not asked.size:
                continue
            found[asked] = _mixture_fits(weighted[asked], phasor_sigma[asked], w, own[asked], own_sigma[asked],
                                         (levels[0][asked], levels[1][asked]),
                                         (level_sigmas[0][asked], level_sigmas[1][asked]))
            rest = asked[~found[asked]]
            if around is not None and rest.size:
                found[rest] = _pooled(padded, noisy, (ys[rest], xs[rest], reach), across, around, w,
                                      (levels[0][rest], levels[1][rest]),
                                      (level_sigmas[0][rest], level_sigmas[1][rest]))
    out = np.zeros((h, w_), bool)
    out[ys[found] - reach, xs[found] - reach] = True
    return out


def _pooled(padded: NDArray, noisy: NDArray, at: tuple[NDArray, NDArray, int], across: tuple[int, int],
            around: tuple[NDArray, NDArray, NDArray], w: NDArray, levels: tuple[NDArray, NDArray],
            level_sigmas: tuple[NDArray, NDArray]) -> NDArray[np.bool_]:
    """Whether the pixels at (``at``: rows and columns in the ``padded`` fused depths [m], ``noisy`` their noise
    [m], and the padding) and their two neighbours ``across`` the step, alike in depth (along the edge, where a
    straight edge's mixed pixels hold about one mixture:
    :func:`mpi_lidar.correction._mixed_steps.edge_level`),
    together fit two returns at the sides' ``levels`` (each (k,) [m], within one of ``level_sigmas`` [m], the
    same for the three) within ``FIT_P_VALUE``, better than one return each about its own depth by
    ``POOLED_DELTA_CHI2``. ``around``: rows (h, W) into phasors (n, F) [V^2] and their noise (n, F) [V^2]."""
    from scipy.special import chdtri  # the quantile without scipy.stats's imports

    ys, xs, reach = at
    index, phasors, phasor_sigma = around
    h, w_ = index.shape
    (ay, ax), found = across, np.zeros(ys.size, bool)
    spots = [(ys + k * ay, xs + k * ax) for k in (-1, 0, 1)]
    inside = np.ones(ys.size, bool)
    for y, x in spots:
        inside &= (y >= reach) & (y < h + reach) & (x >= reach) & (x < w_ + reach)
    rows = [np.where(inside, index[np.clip(y - reach, 0, h - 1), np.clip(x - reach, 0, w_ - 1)], -1) for y, x in spots]
    alike = np.isfinite(_blocks.edge_level(padded, noisy, ys, xs, across)[0])
    asked = np.flatnonzero(inside & alike & (np.min(rows, axis=0) >= 0))
    if not asked.size:
        return found
    single, pairs = np.zeros(asked.size), np.full((len(LEVEL_STEPS) ** 2, asked.size), 0.0)
    for (y, x), row in zip(spots, rows, strict=True):
        z, z_sigma = phasors[row[asked]] / phasor_sigma[row[asked]], phasor_sigma[row[asked]]
        own, own_sigma = padded[y[asked], x[asked]].astype(np.float64), noisy[y[asked], x[asked]].astype(np.float64)
        single += np.min([_single_chi2(z, _basis(own + step * own_sigma, w, z_sigma)) for step in OWN_STEPS], axis=0)
        for i, (near_step, far_step) in enumerate(itertools.product(LEVEL_STEPS, LEVEL_STEPS)):
            pairs[i] += _pair_chi2(z, _basis(levels[0][asked] + near_step * level_sigmas[0][asked], w, z_sigma),
                                   _basis(levels[1][asked] + far_step * level_sigmas[1][asked], w, z_sigma))
    mixture = pairs.min(axis=0)
    dof = 3 * (2 * phasors.shape[1] - 2)
    found[asked] = (mixture <= chdtri(dof, FIT_P_VALUE)) & (single - mixture > POOLED_DELTA_CHI2)
    return found


def _mixture_fits(weighted: NDArray, phasor_sigma: NDArray, w: NDArray, own: NDArray, own_sigma: NDArray,
                  levels: tuple[NDArray, NDArray], level_sigmas: tuple[NDArray, NDArray]) -> NDArray[np.bool_]:
    """Whether the noise-weighted phasors ``weighted`` (k, F) (``phasor_sigma`` (k, F) [V^2]) fit two returns at
    the sides' ``levels`` (each (k,) [m], within one of ``level_sigmas`` [m]) within ``FIT_P_VALUE``, better than
    one return about ``own`` (k,) [m] (within one of ``own_sigma`` [m]) by ``DELTA_CHI2``."""
    from scipy.special import chdtri  # the quantile without scipy.stats's imports

    single = np.min([_single_chi2(weighted, _basis(own + step * own_sigma, w, phasor_sigma))
                     for step in OWN_STEPS], axis=0)
    mixture = np.full(own.shape, np.inf)
    for near_step in LEVEL_STEPS:
        first = _basis(levels[0] + near_step * level_sigmas[0], w, phasor_sigma)
        for far_step in LEVEL_STEPS:
            second = _basis(levels[1] + far_step * level_sigmas[1], w, phasor_sigma)
            mixture = np.fmin(mixture, _pair_chi2(weighted, first, second))
    dof = 2 * weighted.shape[1] - 2
    return np.asarray((mixture <= chdtri(dof, FIT_P_VALUE)) & (single - mixture > DELTA_CHI2))


def _basis(range_m: NDArray, w: NDArray, phasor_sigma: NDArray) -> NDArray[np.complex128]:
    """A unit return at ``range_m`` (k,) [m] at each frequency (``w`` (F,) [rad/m]), over the noise (k, F)."""
    return np.exp(1j * range_m[:, None] * w[None, :]) / phasor_sigma


def _single_chi2(z: NDArray, e: NDArray) -> NDArray[np.float64]:
    """chi^2 (k,) of weighted phasors ``z`` (k, F) against one return of basis ``e`` (k, F) and the best
    amplitude not below zero."""
    amplitude = np.maximum((np.conj(e) * z).real.sum(axis=1) / (np.abs(e) ** 2).sum(axis=1), 0.0)
    return np.asarray((np.abs(z - amplitude[:, None] * e) ** 2).sum(axis=1))


def _pair_chi2(z: NDArray, e1: NDArray, e2: NDArray) -> NDArray[np.float64]:
    """chi^2 (k,) of weighted phasors ``z`` (k, F) against two returns of bases ``e1``, ``e2`` (k, F) with the best
    amplitudes, both positive and the weaker at least ``MIN_SHARE`` of their sum (inf where the best are not)."""
    g11, g22 = (np.abs(e1) ** 2).sum(axis=1), (np.abs(e2) ** 2).sum(axis=1)
    g12 = (np.conj(e1) * e2).real.sum(axis=1)
    b1, b2 = (np.conj(e1) * z).real.sum(axis=1), (np.conj(e2) * z).real.sum(axis=1)
    det = g11 * g22 - g12**2
    with np.errstate(invalid="ignore", divide="ignore"):
        a1, a2 = (g22 * b1 - g12 * b2) / det, (g11 * b2 - g12 * b1) / det
        weaker = np.minimum(a1, a2) / (a1 + a2)
    chi2 = (np.abs(z) ** 2).sum(axis=1) - a1 * b1 - a2 * b2
    usable = (a1 > 0) & (a2 > 0) & (weaker >= MIN_SHARE) & (det > 1e-9 * g11 * g22)
    return np.where(usable, chi2, np.inf)
