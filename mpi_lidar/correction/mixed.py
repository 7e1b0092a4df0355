"""The mixed-pixel stage: pixels whose footprint straddles a depth edge (:func:`find_mixed`), after the gate.

Such a pixel receives two returns, from the near and the far surface; at each frequency its phase is their
amplitude-weighted mixture, so its one depth lies between the surfaces (a "flying pixel"), and the frequencies,
which mix the two phases differently, disagree. A pixel is MIXED where both hold:

- its frequencies disagree beyond their noise: chi-square of their depths under the scan's noise model above its
  1 - ``MIXED_P_VALUE`` quantile (looser than validity's ``inconsistent_p_value``, which flags only the grossest
  disagreements INCONSISTENT, and which an edge may turn into MIXED), or chi-square of their amplitudes above its
  1 - ``AMPLITUDE_P_VALUE`` quantile (:func:`amplitude_spread`: one surface returns the same light at every
  frequency, after the scanner's gains, :func:`frequency_gains`; two returns' sum beats as cos(2 pi f g / c) over
  their gap g, which two equally bright returns, whose phase is their mean at every frequency, show only there);
- it sits at a depth edge: a neighbour within one pixel whose measured depth differs from its own by more than
  ``EDGE_SIGMAS`` times the two depths' noise and more than ``MIN_EDGE_M``.

A pixel whose second return is weak has frequencies that barely disagree, yet a depth off by a share of the gap:
it is MIXED too where its depth lies between two opposite neighbours', by those margins from each and from their
mean (a point off the line through its neighbours, which no plane gives, however grazing). Where both returns are
about equally bright and the gap below a metre, or the noise large, none of these sees it: the frequencies' depths
agree (two equal returns' phase is their mean at every frequency), their amplitudes part by less than their noise,
and the depth lies on the line through the neighbours. What tells it from a
grazing surface is the neighbourhood two pixels out: at a depth edge the pixel lies between two flat sides, each
neighbour's depth close to its own next neighbour's and far from the pixel's, where a surface, however grazing or
curved, steps by similar amounts from pixel to pixel (:func:`_stepped`; a corner's pixel has one flat side at
most). Its jumps need ``STEP_SIGMAS`` of the noise, fewer than a lone edge's ``EDGE_SIGMAS``: two flat sides make
such a step rarer. It reads the frequencies' fused depth (about 0.68 of the highest frequency's noise) and each
side's median across the direction, so that a dark plate's few per cent of the light, which move the depth by a few
sigmas, and a noisy dark side are seen; a side's flatness must hold beyond its noise, as a grazing surface's noisy
steps look flat now and then. One side may begin a pixel further out, past a pixel that lies between: two mixed
pixels in a row, where an edge runs diagonally or the footprint is wider than the pixels' pitch. Far away, where a
pixel's noise is centimetres, a second form of the test (:func:`mpi_lidar.correction._mixed_steps.stepped`) takes
each side's level as the median of a block of six pixels, half a pixel's noise: the step must be significant in the
sides' noise, and the pixel (or its median with its two neighbours along the edge) lie only two of its own sigmas
(and ``MIN_EDGE_M``) from each. Where one side returns
no usable light (NO_RETURN), a one-sided test (:func:`mpi_lidar.correction._mixed_dark.lost_light`) reads the
lit side alone: the pixel's amplitude lies between the two sides' and its depth off the lit side's. Elsewhere the
amplitude's level tells little: a mixture's lies between its neighbours' as a grazing surface's does. Where the
sides lie metres apart, each frequency's mixture may wrap to about one depth near a side (the phasors part by about
0.26 rad per metre of gap at the 6.25 MHz spacing), which none of these tests sees; the pixel's phasors still fit
two returns at its sides' ranges, fixed by the neighbourhood, significantly better than one return, alone or with
its two neighbours along the edge (:func:`mpi_lidar.correction._mixed_ranges.two_ranges`).

A clean surface passes the first test but for a share ``MIXED_P_VALUE`` of its pixels, and only those beside a
jump of several centimetres (a grazing surface's) can be flagged. Where the phasors fit two returns within the
noise (:func:`mpi_lidar.physics.two_returns.fit_two_returns`: in closed form at evenly spaced frequencies, by least
squares at others), at least ``MIN_GAP_M`` apart with the weaker holding at least ``MIN_SHARE`` of the light, the
pixel is TWO_RETURNS instead: its depth is the stronger return's and the weaker's range and share are kept
(:class:`SecondReturns`), each range with its 1-sigma, the fit's Cramer-Rao bound
(:func:`mpi_lidar.correction._mixed_bounds.range_sigmas`; the stronger's is the depth's uncertainty).

The candidates are found on the validity stage's measured depths, which exist whole; the raw measurements (and
the fused depth the step test reads) are read again only for the rows of the tiles that hold a candidate (a pixel
beside a jump of ``MIN_EDGE_M``), with ``MARGIN_ROWS`` rows either side. A scan without such a pixel is left
exactly as the gate left it.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
from numpy.typing import NDArray

from mpi_lidar.correction import _mixed_bounds as _bounds
from mpi_lidar.correction import _mixed_dark as _dark
from mpi_lidar.correction import _mixed_ranges as _ranges
from mpi_lidar.correction import _mixed_steps as _blocks
from mpi_lidar.correction.gating import GateDecision
from mpi_lidar.correction.options import Flag
from mpi_lidar.correction.validity import Validity
from mpi_lidar.physics.inverse import measured_phasors
from mpi_lidar.physics.noise import NoiseModel
from mpi_lidar.physics.two_returns import gap_ambiguity_m
from mpi_lidar.scans.scan import Scan

MIXED_P_VALUE = 1e-3  # the frequencies' chi-square p-value below which a pixel at a depth edge is mixed
# ...and their amplitudes': stricter, as far-off surfaces' noisy depths put many pixels beside a jump
AMPLITUDE_P_VALUE = 1e-4
EDGE_SIGMAS = 10.0  # a depth edge: a neighbour's depth this many noise sigmas away...
MIN_EDGE_M = 0.05  # ...and this many metres [m]
FLAT_SHARE = 0.35  # a step's sides are flat: a side's next depth outwards within this share of its jump [1]...
FLAT_SIGMAS = 2.0  # ...by this many sigmas of the two depths' noise
STEP_SIGMAS = 4.0  # ...and its jumps this many noise sigmas: flat sides make a step rarer than a lone jump
MIN_GAP_M = 2.0  # two returns are resolved only this far apart [m]: nearer, four frequencies cannot tell them
MIN_SHARE = 0.2  # ...and only where the weaker return holds at least this share of the light
TWO_RETURN_P_VALUE = 1e-3  # the two-return fit's residual must lie within chi-square's 1 - this quantile
# The flags a mixed pixel may have had: valid ones, and inconsistent (a depth edge is the better reason).
CANDIDATE_FLAGS = (Flag.CORRECTED, Flag.NOT_NEEDED, Flag.NO_MULTIPATH, Flag.UNCALIBRATED, Flag.OUT_OF_RANGE,
                   Flag.INCONSISTENT)
NEIGHBOURS = tuple((dy, dx) for dy in (-1, 0, 1) for dx in (-1, 0, 1) if dy or dx)
# A step's directions, each with the one across it along which a side's three depths are taken.
ACROSS = {(0, 1): (1, 0), (1, 0): (0, 1), (1, 1): (1, -1), (1, -1): (1, 1)}
# The median of three alike depths' sd over one's [1] (where they slope across, the middle one's: its noise is
# understated, and the tests' margins with it).
ACROSS_SIGMA_SHARE = 0.67
STEP_REACH = 4  # a step's sides reach three pixels out along a diagonal and one across it
MARGIN_ROWS = max(STEP_REACH, _blocks.BLOCK_REACH, _dark.DARK_REACH)  # rows read either side of a tile


@dataclass(frozen=True)
class SecondReturns:
    """The weaker return of each TWO_RETURNS pixel; maps (H, W), NaN elsewhere.

    depth_m : Its range along the ray. [m]
    share : Its share of the two returns' amplitudes. [1]
    sigma_m : Its range's 1-sigma: the two-return fit's Cramer-Rao bound (None: not known). [m]
    stronger_sigma_m : The stronger return's 1-sigma from the same fit, which the per-pixel estimate makes the
        corrected depth's uncertainty (None: not known). [m]
    """

    depth_m: NDArray[np.float32]
    share: NDArray[np.float32]
    sigma_m: NDArray[np.float32] | None = None
    stronger_sigma_m: NDArray[np.float32] | None = None


@dataclass(frozen=True)
class MixedPixels:
    """The mixed-pixel stage's result.

    decision : The gate's decision with MIXED and TWO_RETURNS pixels flagged so (the gate's own where none is).
    validity : The validity stage's result with the usable depth NaN where MIXED and the stronger return's where
        TWO_RETURNS (the validity stage's own where none is): what the per-pixel estimate starts from.
    second_returns : The weaker returns (None where no pixel was resolved).
    mixed_pixels : Pixels flagged MIXED.
    resolved_pixels : Pixels flagged TWO_RETURNS.
    """

    decision: GateDecision
    validity: Validity
    second_returns: SecondReturns | None
    mixed_pixels: int
    resolved_pixels: int


def find_mixed(scan: Scan, tiles: list[slice], validity: Validity, decision: GateDecision,
               noise: NoiseModel) -> MixedPixels:
    """The mixed and resolved pixels of ``scan`` (the validity stage's: depths in one range, amplitudes in V^2),
    read in ``tiles`` (flat ranges of whole rows, each with ``MARGIN_ROWS`` rows either side for the neighbours);
    ``decision`` is the gate's. The working memory is a tile's: nothing of the whole scan is made unless a pixel is
    found."""
    h, w = scan.shape
    depth = validity.measured_depth.reshape(h, w)
    allowed = [int(f) for f in CANDIDATE_FLAGS]
    mixed_parts: list[NDArray[np.intp]] = []
    mixed_rows: list[NDArray] = []  # their measurements, fitted at once: a fit's cost is mostly per call
    for pixels in tiles:
        top, bottom = pixels.start // w, pixels.stop // w
        first, last = max(top - MARGIN_ROWS, 0), min(bottom + MARGIN_ROWS, h)  # the neighbours' rows
        band = depth[first:last]
        flags = decision.flags[first * w:last * w].reshape(band.shape)
        allowed_here = np.isin(flags, allowed)
        candidates = allowed_here & (largest_jump(band) > MIN_EDGE_M)
        no_return = flags == Flag.NO_RETURN
        beside_dark = allowed_here & _dark.beside_no_return(no_return)
        for where in (candidates, beside_dark):
            where[:top - first] = False
            where[bottom - first:] = False
        if not (candidates.any() or beside_dark.any()):
            continue
        raw = replace(scan, depth=scan.depth[:, first:last], amplitude=scan.amplitude[:, first:last]).raw_pixels()
        found = np.flatnonzero(mixed_in_rows(raw, band, candidates, noise, no_return, beside_dark))
        if not found.size:
            continue
        mixed_parts.append(first * w + found)
        mixed_rows.append(raw[found])
    if not mixed_parts:
        return MixedPixels(decision, validity, None, 0, 0)
    mixed = np.concatenate(mixed_parts)
    resolved = resolve(np.concatenate(mixed_rows), mixed, depth.reshape(-1), noise)
    return _applied(decision, validity, mixed, [resolved], (h, w))


def largest_jump(depth: NDArray) -> NDArray[np.float32]:
    """Each pixel's largest absolute depth difference to a finite neighbour within one pixel (h, W) [m] (0 where
    it has none, NaN where its own depth is not finite), one neighbour at a time."""
    h, w = depth.shape
    padded = np.full((h + 2, w + 2), np.nan, dtype=np.float32)
    padded[1:-1, 1:-1] = depth
    largest = np.zeros((h, w), dtype=np.float32)
    with np.errstate(invalid="ignore"):
        for dy, dx in NEIGHBOURS:
            np.fmax(largest, np.abs(depth - padded[1 + dy:h + 1 + dy, 1 + dx:w + 1 + dx]), out=largest)
    return np.where(np.isfinite(depth), largest, np.float32(np.nan))


def _jumps(depth: NDArray, sigma: NDArray) -> NDArray[np.float32]:
    """Per neighbour (8, H, W): the depth difference [m] to it where it exceeds ``EDGE_SIGMAS`` times the two depths'
    noise (``sigma`` (H, W) [m]), 0 where not, NaN where the neighbour or the pixel has no finite depth."""
    h, w = depth.shape
    padded = np.full((h + 2, w + 2), np.nan, dtype=np.float32)
    padded[1:-1, 1:-1] = depth
    noisy = np.zeros((h + 2, w + 2), dtype=np.float32)
    noisy[1:-1, 1:-1] = sigma
    out = np.empty((len(NEIGHBOURS), h, w), dtype=np.float32)
    for i, (dy, dx) in enumerate(NEIGHBOURS):
        other = padded[1 + dy:h + 1 + dy, 1 + dx:w + 1 + dx]
        jump = np.abs(depth - other)
        bound = EDGE_SIGMAS * np.hypot(sigma, noisy[1 + dy:h + 1 + dy, 1 + dx:w + 1 + dx])
        with np.errstate(invalid="ignore"):
            out[i] = np.where(jump > bound, jump, np.where(np.isnan(jump), np.nan, 0.0))
    return out


def _between(depth: NDArray, sigma: NDArray) -> NDArray[np.bool_]:
    """Pixels (H, W) whose depth lies between two opposite neighbours' (left and right, above and below, or
    diagonally), more than ``MIN_EDGE_M`` and ``EDGE_SIGMAS`` of the noise from each and from their mean: a point
    off the line through its neighbours, which a plane, however grazing, does not give (``sigma`` (H, W) [m])."""
    h, w = depth.shape
    padded = np.full((h + 2, w + 2), np.nan, dtype=np.float32)
    padded[1:-1, 1:-1] = depth
    noisy = np.zeros((h + 2, w + 2), dtype=np.float32)
    noisy[1:-1, 1:-1] = sigma
    found = np.zeros((h, w), bool)
    for dy, dx in ((0, 1), (1, 0), (1, 1), (1, -1)):
        ahead, behind = (slice(1 + dy, h + 1 + dy), slice(1 + dx, w + 1 + dx)), \
            (slice(1 - dy, h + 1 - dy), slice(1 - dx, w + 1 - dx))
        one, other = padded[ahead], padded[behind]
        one_margin, other_margin = (np.maximum(MIN_EDGE_M, EDGE_SIGMAS * np.hypot(sigma, noisy[side]))
                                    for side in (ahead, behind))
        with np.errstate(invalid="ignore"):
            apart = (np.abs(depth - one) > one_margin) & (np.abs(depth - other) > other_margin)
            off_line = np.abs(depth - (one + other) / 2) > np.minimum(one_margin, other_margin)
            found |= apart & ((depth - one) * (other - depth) > 0) & off_line
    return found


def _stepped(depth: NDArray, sigma: NDArray, where: NDArray | None = None) -> NDArray[np.bool_]:
    """Pixels (h, W) at a step: their depth lies between two opposite sides (left and right, above and below, or
    diagonally), more than ``MIN_EDGE_M`` and ``STEP_SIGMAS`` of the noise from each, while each side is flat
    (:func:`_flat_side`). A surface, however grazing or curved, changes its depth by similar steps from pixel to
    pixel; a footprint on both sides of a depth edge jumps twice between two runs of nearly equal depth, wherever
    its depth falls between them (the mean of two equally bright returns included, which :func:`_between` misses).

    A side's depth at each distance is the median of the three pixels across the direction (:func:`_across`):
    two thirds of one pixel's noise along a straight edge, and one pixel of the other side, where the edge runs
    diagonally, does not move it. One side may begin a pixel further out where the pixel between lies between
    the two: two mixed pixels in a row, where the edge runs diagonally or the footprint is wider than the pixels'
    pitch. ``depth`` (h, W) [m] and ``sigma`` (h, W) [m]; only the pixels ``where`` (h, W) is true are looked at
    (None: all), so that a band's few candidates cost what they are; pixels within ``STEP_REACH`` of the band's
    border are never found."""
    h, w = depth.shape
    reach = STEP_REACH
    padded, noisy, ys, xs = _blocks.padded_band(depth, sigma, where, reach, 0.0)
    own, own_sigma = padded[ys, xs], noisy[ys, xs]
    found = np.zeros(ys.size, bool)
    with np.errstate(invalid="ignore"):
        for (dy, dx), across in ACROSS.items():
            sides = {}
            for sign in (1, -1):
                at = [(ys + k * sign * dy, xs + k * sign * dx) for k in (1, 2, 3)]  # outwards
                line = [_across(padded, y, x, across) for y, x in at]
                for gap in (1, 2):  # the side begins at the neighbour, or at the pixel beyond it
                    sides[sign, gap] = _flat_side(own, own_sigma, line, padded[at[0]], [noisy[a] for a in at], gap)
            for first, second in ((1, 1), (1, 2), (2, 1)):  # at most one pixel between the pixel and a side
                (one, one_jump), (other, other_jump) = sides[1, first], sides[-1, second]
                found |= one & other & (one_jump * other_jump < 0)
    out = np.zeros((h, w), bool)
    out[ys[found] - reach, xs[found] - reach] = True
    return out


def _flat_side(own: NDArray, own_sigma: NDArray, line: list[NDArray], between: NDArray, line_sigma: list[NDArray],
               gap: int) -> tuple[NDArray[np.bool_], NDArray]:
    """Whether the side ``gap`` pixels out (1 or 2) of pixels of depth ``own`` (k,) [m] and noise ``own_sigma``
    (k,) [m] is a flat side of a step, and the jump to it (k,) [m]. ``line`` holds the side's depths (k,) [m] one,
    two and three pixels out (medians across), ``line_sigma`` a pixel's noise there [m], ``between`` the depth
    one pixel out (k,) [m]. The side's depth lies ``MIN_EDGE_M`` and ``STEP_SIGMAS`` of the noise from the pixel's;
    its next depth outwards lies within ``FLAT_SHARE`` of the jump per pixel, by ``FLAT_SIGMAS`` of the two
    depths' noise (a grazing surface's noisy steps look flat now and then: not beyond their noise); a side two out
    has the pixel between lying between it and the pixel, within ``STEP_SIGMAS`` of their noise."""
    near, outer = line[gap - 1], line[gap]
    near_sigma, outer_sigma = (ACROSS_SIGMA_SHARE * line_sigma[k] for k in (gap - 1, gap))
    jump = near - own
    margin = np.maximum(MIN_EDGE_M, STEP_SIGMAS * np.hypot(own_sigma, near_sigma))
    flat = np.abs(outer - near) + FLAT_SIGMAS * np.hypot(near_sigma, outer_sigma) < FLAT_SHARE * np.abs(jump) / gap
    side = (np.abs(jump) > margin) & flat
    if gap == 2:  # the pixel between lies between the pixel and the side, as a second mixed pixel does
        slack = STEP_SIGMAS * np.hypot(own_sigma, line_sigma[0])
        side &= (np.sign(jump) * (between - own) > -slack) & (np.sign(jump) * (near - between) > -slack)
    return side, jump


def _across(padded: NDArray, ys: NDArray[np.intp], xs: NDArray[np.intp], across: tuple[int, int]) -> NDArray:
    """The median (k,) of the three depths at (``ys``, ``xs``) and one pixel either way ``across`` in ``padded``;
    the middle one's where any of the three is not finite."""
    dy, dx = across
    three = np.sort(np.stack([padded[ys - dy, xs - dx], padded[ys, xs], padded[ys + dy, xs + dx]]), axis=0)
    middle = padded[ys, xs]
    return np.where(np.isfinite(three).all(axis=0), three[1], middle)


def mixed_in_rows(raw: NDArray, depth: NDArray, candidates: NDArray, noise: NoiseModel,
                  no_return: NDArray | None = None, beside_dark: NDArray | None = None) -> NDArray[np.bool_]:
    """Which candidates (h, W) of some whole rows are mixed: their frequencies' depths disagree beyond chi-square's
    1 - ``MIXED_P_VALUE`` quantile, or their amplitudes beyond its 1 - ``AMPLITUDE_P_VALUE`` quantile
    (:func:`amplitude_spread`), and a neighbour's measured depth (``depth`` (h, W) [m]) lies more than
    ``EDGE_SIGMAS`` of the two depths' noise and ``MIN_EDGE_M`` away, or their depth lies off the line between two
    opposite neighbours (:func:`_between`: a weak second return biases the depth more than the frequencies'
    spread shows), or between two flat sides (:func:`_stepped`: two returns of about equal strength, or a gap
    below a metre), or its phasors are two returns at its sides' ranges (:func:`_two_ranges`: sides metres apart,
    where each frequency's mixture wraps to about one depth); ``raw`` (h*W, 2F) are the rows' measurements. The
    pixels ``beside_dark`` (h, W), beside one with no usable return (``no_return`` (h, W)), are mixed where their
    footprint lost light to it and their depth lies off the lit side's
    (:func:`mpi_lidar.correction._mixed_dark.lost_light`)."""
    from scipy.special import chdtri  # the quantile without scipy.stats's imports

    f = len(noise.frequencies_hz)
    fused = noise.fuse(raw)
    frequencies_disagree = fused.disagree(MIXED_P_VALUE, f).reshape(depth.shape)
    sigma = fused.top_sigma_m.reshape(depth.shape)
    ys, xs = np.nonzero(candidates)
    amplitude = raw[:, f:].reshape(*depth.shape, f)
    amplitude_chi2 = np.zeros(depth.shape)
    gains = frequency_gains(amplitude, ys, xs)
    amplitude_chi2[ys, xs] = amplitude_spread(amplitude[ys, xs], gains, noise)
    # The step test reads the frequencies' fused depth, about 0.68 of the highest frequency's noise: the jumps it
    # looks for are a few sigmas. The lone-edge tests keep the highest frequency's depth their margins were set on.
    fused_depth = np.where(np.isfinite(depth), fused.depth_m.reshape(depth.shape), np.nan)
    fused_sigma = fused.sigma_m.reshape(depth.shape)
    stepped = _stepped(fused_depth, fused_sigma, candidates) | _blocks.stepped(fused_depth, fused_sigma, candidates)
    with np.errstate(invalid="ignore"):
        edge = np.nan_to_num(_jumps(depth, sigma), nan=0.0).max(axis=0) > MIN_EDGE_M
        disagree = frequencies_disagree | (amplitude_chi2 > chdtri(f - 1, AMPLITUDE_P_VALUE))
    found = candidates & ((edge & disagree) | _between(depth, sigma) | stepped)
    found |= _two_ranges(raw, fused_depth, fused_sigma, candidates & ~found, (ys, xs), noise)
    if no_return is not None and beside_dark is not None and beside_dark.any():
        light = raw[:, f:].astype(np.float64)
        light_sigma = np.sqrt((noise.quadrature_sigma_v2(light) ** 2).sum(axis=1)).reshape(depth.shape)
        found |= _dark.lost_light(fused_depth, fused_sigma, light.sum(axis=1).reshape(depth.shape), light_sigma,
                                  no_return, beside_dark)
    return np.asarray(found)


def _two_ranges(raw: NDArray, depth: NDArray, sigma: NDArray, where: NDArray, at: tuple[NDArray, NDArray],
                noise: NoiseModel) -> NDArray[np.bool_]:
    """The pixels ``where`` (h, W) beside a jump of half ``_ranges.MIN_GAP_M`` in the fused ``depth`` (h, W) [m]
    (noise ``sigma`` (h, W) [m]) whose phasors are two returns at their sides' ranges
    (:func:`mpi_lidar.correction._mixed_ranges.two_ranges`, each alone or with its neighbours along the edge);
    ``raw`` (h*W, 2F) the rows' measurements, ``at`` the candidates' rows and columns, a superset of
    ``where``'s."""
    ys, xs = at
    h, w = depth.shape
    padded = np.full((h + 2, w + 2), np.nan, dtype=np.float64)
    padded[1:-1, 1:-1] = depth
    jump = np.zeros(ys.size)
    with np.errstate(invalid="ignore"):
        for dy, dx in NEIGHBOURS:
            jump = np.fmax(jump, np.abs(padded[ys + 1, xs + 1] - padded[ys + 1 + dy, xs + 1 + dx]))
    asked = where[ys, xs] & (jump > _ranges.MIN_GAP_M / 2)
    if not asked.any():
        return np.zeros(depth.shape, bool)
    selected, near = np.zeros(depth.shape, bool), np.zeros((h + 2, w + 2), bool)
    selected[ys[asked], xs[asked]] = True
    for dy, dx in ((0, 0), *NEIGHBOURS):  # the pixels and those they pool with along the edge, margin rows too
        near[1 + dy:h + 1 + dy, 1 + dx:w + 1 + dx] |= selected
    ys, xs = np.nonzero(near[1:-1, 1:-1])
    f = len(noise.frequencies_hz)
    gains = frequency_gains(raw[:, f:].reshape(h, w, f), ys, xs)
    rows = raw[ys * w + xs].astype(np.float64)
    freqs, c = np.asarray(noise.frequencies_hz), noise.speed_of_light_m_per_s
    phasors, phasor_sigma = measured_phasors(rows, freqs, c) / gains, noise.quadrature_sigma_v2(rows[:, f:]) / gains
    index = np.full(depth.shape, -1, np.intp)
    index[ys, xs] = np.arange(ys.size)
    own = index[selected]
    return _ranges.two_ranges(depth, sigma, phasors[own], phasor_sigma[own], 4 * np.pi * freqs / c, selected,
                              (index, phasors, phasor_sigma))


def frequency_gains(amplitude: NDArray, ys: NDArray[np.intp], xs: NDArray[np.intp]) -> NDArray[np.float64]:
    """Each frequency's share of the light (k, F) [1] about the pixels (``ys``, ``xs``) of some rows' amplitudes
    ``amplitude`` (h, W, F) [V^2]: the median over a pixel's eight neighbours of each one's amplitudes over their
    mean (a neighbour without positive, finite amplitudes counts as equal ones). One surface returns the same light
    at every frequency but for the scanner's gains, which its neighbours share; at an edge, most of them see one
    surface."""
    h, w, f = amplitude.shape
    padded = np.full((h + 2, w + 2, f), np.nan)
    padded[1:-1, 1:-1] = amplitude
    profiles = np.ones((len(NEIGHBOURS), ys.size, f))
    for i, (dy, dx) in enumerate(NEIGHBOURS):
        around = padded[ys + 1 + dy, xs + 1 + dx]
        usable = np.all(np.isfinite(around) & (around > 0), axis=1)
        profiles[i, usable] = around[usable] / around[usable].mean(axis=1, keepdims=True)
    return np.asarray(np.median(profiles, axis=0))


def amplitude_spread(amplitude: NDArray, gains: NDArray, noise: NoiseModel) -> NDArray[np.float64]:
    """chi^2 (n,) of each row's amplitudes (n, F) [V^2], over the frequencies' ``gains`` (n, F) or (F,), about their
    inverse-variance mean in units of their noise (the quadrature sd): chi^2(F - 1) where one surface returned
    the light, whose amplitude is the same at every frequency; two returns' sum is not (it beats as
    cos(2 pi f g / c) over a gap g)."""
    values = np.asarray(amplitude, dtype=np.float64)
    scaled = values / gains
    weights = (gains / noise.quadrature_sigma_v2(values)) ** 2
    mean = (weights * scaled).sum(axis=1, keepdims=True) / weights.sum(axis=1, keepdims=True)
    return np.asarray((weights * (scaled - mean) ** 2).sum(axis=1))


def resolve(rows: NDArray, flat: NDArray[np.intp], depth: NDArray, noise: NoiseModel,
            ) -> tuple[NDArray[np.intp], NDArray, NDArray, NDArray, NDArray, NDArray]:
    """Fit two returns to the mixed pixels' ``rows`` (k, 2F) at flat indices ``flat`` (k,): those resolved
    (``MIN_GAP_M`` apart, ``MIN_SHARE`` of the light, a residual within the noise), with their stronger return's
    range [m], the weaker's [m], its share [1], its 1-sigma [m] and the stronger's (the fit's Cramer-Rao bounds,
    :func:`mpi_lidar.correction._mixed_bounds.range_sigmas`). The fit is the closed form where the frequencies are
    evenly spaced, a least-squares fit at other sets of four or more
    (:func:`~mpi_lidar.physics.two_returns.fit_two_returns`); none with fewer."""
    f = len(noise.frequencies_hz)
    if not flat.size or f < 4:
        return flat[:0], np.zeros(0), np.zeros(0), np.zeros(0), np.zeros(0), np.zeros(0)
    from scipy.special import chdtri

    fit, stronger_sigma, weaker_sigma = _bounds.fit_with_sigmas(rows, depth[flat], noise)
    period = gap_ambiguity_m(noise.frequencies_hz, noise.speed_of_light_m_per_s)
    gap = fit.far_m - fit.near_m
    with np.errstate(invalid="ignore"):  # a gap near half the poles' ambiguity may be either of two
        good = ((gap >= MIN_GAP_M) & (gap <= period / 2 - MIN_GAP_M) & (fit.weaker_share >= MIN_SHARE)
                & (fit.chi2 <= chdtri(2 * f - 4, TWO_RETURN_P_VALUE)) & (fit.near_m > 0))
    return (flat[good], fit.stronger_m[good], fit.weaker_m[good], fit.weaker_share[good], weaker_sigma[good],
            stronger_sigma[good])


def _applied(decision: GateDecision, validity: Validity, mixed: NDArray[np.intp],
             resolved_parts: list[tuple[NDArray[np.intp], NDArray, NDArray, NDArray, NDArray, NDArray]],
             shape: tuple[int, int]) -> MixedPixels:
    """The gate's decision and the validity's usable depth with the mixed (flat indices) and resolved pixels
    marked, and the second returns' maps where any pixel was resolved."""
    at, stronger, weaker, share, sigma, stronger_sigma = (np.concatenate(part)
                                                          for part in zip(*resolved_parts, strict=True))
    flags = decision.flags.copy()
    flags[mixed] = Flag.MIXED
    flags[at] = Flag.TWO_RETURNS
    usable = validity.usable_depth.copy()
    usable[mixed] = np.nan
    usable[at] = stronger
    gate = GateDecision(flags, int((flags == Flag.UNCALIBRATED).sum()), decision.served)
    second = None
    if at.size:
        maps = [np.full(shape[0] * shape[1], np.nan, dtype=np.float32) for _ in range(4)]
        for values, of_pixels in zip(maps, (weaker, share, sigma, stronger_sigma), strict=True):
            values[at] = of_pixels
        second = SecondReturns(*(values.reshape(shape) for values in maps))
    return MixedPixels(gate, replace(validity, usable_depth=usable), second, int(mixed.size - at.size), int(at.size))
