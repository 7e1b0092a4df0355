"""The mixed-pixel stage: pixels whose footprint straddles a depth edge (:func:`find_mixed`), after the gate.

Such a pixel receives two returns, from the near and the far surface; at each frequency its phase is their
amplitude-weighted mixture, so its one depth lies between the surfaces (a "flying pixel"), and the frequencies,
which mix the two phases differently, disagree. A pixel is MIXED where both hold:

- its frequencies disagree beyond their noise: chi-square of their depths under the scan's noise model above its
  1 - ``MIXED_P_VALUE`` quantile (looser than validity's ``inconsistent_p_value``, which flags only the grossest
  disagreements INCONSISTENT, and which an edge may turn into MIXED);
- it sits at a depth edge: a neighbour within one pixel whose measured depth differs from its own by more than
  ``EDGE_SIGMAS`` times the two depths' noise and more than ``MIN_EDGE_M``.

A pixel whose second return is weak has frequencies that barely disagree, yet a depth off by a share of the gap:
it is MIXED too where its depth lies between two opposite neighbours', by those margins from each and from their
mean (a point off the line through its neighbours, which no plane gives, however grazing).

A clean surface passes the first test but for a share ``MIXED_P_VALUE`` of its pixels, and only those beside a
jump of several centimetres (a grazing surface's) can be flagged. Where the frequencies are evenly spaced and their
phasors fit two returns within the noise (:func:`mpi_lidar.physics.two_returns.fit_two_returns`), at least
``MIN_GAP_M`` apart with the weaker holding at least ``MIN_SHARE`` of the light, the pixel is TWO_RETURNS instead:
its depth is the stronger return's and the weaker's range and share are kept (:class:`SecondReturns`).

The neighbourhood test reads the validity stage's measured depths, which exist whole; the raw measurements are
read again only for the rows of the tiles that hold a candidate (a pixel beside a jump of ``MIN_EDGE_M``), with
one row either side. A scan without such a pixel is left exactly as the gate left it.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
from numpy.typing import NDArray

from mpi_lidar.correction.gating import GateDecision
from mpi_lidar.correction.options import Flag
from mpi_lidar.correction.validity import Validity
from mpi_lidar.physics.noise import NoiseModel
from mpi_lidar.physics.two_returns import evenly_spaced, fit_two_returns
from mpi_lidar.scans.scan import Scan

MIXED_P_VALUE = 1e-3  # the frequencies' chi-square p-value below which a pixel at a depth edge is mixed
EDGE_SIGMAS = 10.0  # a depth edge: a neighbour's depth this many noise sigmas away...
MIN_EDGE_M = 0.05  # ...and this many metres [m]
MIN_GAP_M = 2.0  # two returns are resolved only this far apart [m]: nearer, four frequencies cannot tell them
MIN_SHARE = 0.2  # ...and only where the weaker return holds at least this share of the light
TWO_RETURN_P_VALUE = 1e-3  # the two-return fit's residual must lie within chi-square's 1 - this quantile
# The flags a mixed pixel may have had: valid ones, and inconsistent (a depth edge is the better reason).
CANDIDATE_FLAGS = (Flag.CORRECTED, Flag.NOT_NEEDED, Flag.NO_MULTIPATH, Flag.UNCALIBRATED, Flag.OUT_OF_RANGE,
                   Flag.INCONSISTENT)
NEIGHBOURS = tuple((dy, dx) for dy in (-1, 0, 1) for dx in (-1, 0, 1) if dy or dx)


@dataclass(frozen=True)
class SecondReturns:
    """The weaker return of each TWO_RETURNS pixel; maps (H, W), NaN elsewhere.

    depth_m : Its range along the ray. [m]
    share : Its share of the two returns' amplitudes. [1]
    """

    depth_m: NDArray[np.float32]
    share: NDArray[np.float32]


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
    read in ``tiles`` (flat ranges of whole rows, each with a row either side for the neighbours); ``decision`` is
    the gate's. The working memory is a tile's: nothing of the whole scan is made unless a pixel is found."""
    h, w = scan.shape
    depth = validity.measured_depth.reshape(h, w)
    allowed = [int(f) for f in CANDIDATE_FLAGS]
    mixed_parts: list[NDArray[np.intp]] = []
    resolved_parts: list[tuple[NDArray[np.intp], NDArray, NDArray, NDArray]] = []
    for pixels in tiles:
        top, bottom = pixels.start // w, pixels.stop // w
        first, last = max(top - 1, 0), min(bottom + 1, h)  # one row either side for the neighbours
        band = depth[first:last]
        candidates = np.isin(decision.flags[first * w:last * w], allowed).reshape(band.shape)
        candidates &= largest_jump(band) > MIN_EDGE_M
        candidates[:top - first] = False
        candidates[bottom - first:] = False
        if not candidates.any():
            continue
        raw = replace(scan, depth=scan.depth[:, first:last], amplitude=scan.amplitude[:, first:last]).raw_pixels()
        found = np.flatnonzero(mixed_in_rows(raw, band, candidates, noise))
        if not found.size:
            continue
        flat = first * w + found
        mixed_parts.append(flat)
        resolved_parts.append(resolve(raw[found], flat, depth.reshape(-1), noise))
    if not mixed_parts:
        return MixedPixels(decision, validity, None, 0, 0)
    return _applied(decision, validity, np.concatenate(mixed_parts), resolved_parts, (h, w))


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


def mixed_in_rows(raw: NDArray, depth: NDArray, candidates: NDArray, noise: NoiseModel) -> NDArray[np.bool_]:
    """Which candidates (h, W) of some whole rows are mixed: their frequencies disagree beyond chi-square's
    1 - ``MIXED_P_VALUE`` quantile and a neighbour's measured depth (``depth`` (h, W) [m]) lies more than
    ``EDGE_SIGMAS`` of the two depths' noise and ``MIN_EDGE_M`` away, or their depth lies off the line between two
    opposite neighbours (:func:`_between`: a weak second return biases the depth more than the frequencies'
    spread shows); ``raw`` (h*W, 2F) are the rows' measurements."""
    from scipy.special import chdtri  # the quantile without scipy.stats's imports

    f = len(noise.frequencies_hz)
    fused = noise.fuse(raw)
    chi2 = ((f - 1) * fused.birge_ratio.astype(np.float64) ** 2).reshape(depth.shape)
    sigma = fused.top_sigma_m.reshape(depth.shape)
    with np.errstate(invalid="ignore"):
        edge = np.nan_to_num(_jumps(depth, sigma), nan=0.0).max(axis=0) > MIN_EDGE_M
        disagree = chi2 > chdtri(f - 1, MIXED_P_VALUE)
    return np.asarray(candidates & ((edge & disagree) | _between(depth, sigma)))


def resolve(rows: NDArray, flat: NDArray[np.intp], depth: NDArray, noise: NoiseModel,
            ) -> tuple[NDArray[np.intp], NDArray, NDArray, NDArray]:
    """Fit two returns to the mixed pixels' ``rows`` (k, 2F) at flat indices ``flat`` (k,): those resolved
    (``MIN_GAP_M`` apart, ``MIN_SHARE`` of the light, a residual within the noise), with their stronger return's
    range [m], the weaker's [m] and its share [1]. None where the frequencies are not evenly spaced (the closed
    form needs them)."""
    none = (flat[:0], np.zeros(0), np.zeros(0), np.zeros(0))
    if not flat.size or not evenly_spaced(noise.frequencies_hz):
        return none
    from scipy.special import chdtri

    f = len(noise.frequencies_hz)
    sigma = noise.quadrature_sigma_v2(rows[:, f:].astype(np.float64))
    fit = fit_two_returns(rows, noise.frequencies_hz, sigma, noise.speed_of_light_m_per_s, depth[flat])
    period = noise.speed_of_light_m_per_s / (2 * (noise.frequencies_hz[1] - noise.frequencies_hz[0]))
    gap = fit.far_m - fit.near_m
    with np.errstate(invalid="ignore"):  # a gap near half the poles' ambiguity may be either of two
        good = ((gap >= MIN_GAP_M) & (gap <= period / 2 - MIN_GAP_M) & (fit.weaker_share >= MIN_SHARE)
                & (fit.chi2 <= chdtri(2 * f - 4, TWO_RETURN_P_VALUE)) & (fit.near_m > 0))
    return flat[good], fit.stronger_m[good], fit.weaker_m[good], fit.weaker_share[good]


def _applied(decision: GateDecision, validity: Validity, mixed: NDArray[np.intp],
             resolved_parts: list[tuple[NDArray[np.intp], NDArray, NDArray, NDArray]], shape: tuple[int, int],
             ) -> MixedPixels:
    """The gate's decision and the validity's usable depth with the mixed (flat indices) and resolved pixels
    marked, and the second returns' maps where any pixel was resolved."""
    at, stronger, weaker, share = (np.concatenate(part) for part in zip(*resolved_parts, strict=True))
    flags = decision.flags.copy()
    flags[mixed] = Flag.MIXED
    flags[at] = Flag.TWO_RETURNS
    usable = validity.usable_depth.copy()
    usable[mixed] = np.nan
    usable[at] = stronger
    gate = GateDecision(flags, int((flags == Flag.UNCALIBRATED).sum()), decision.served)
    second = None
    if at.size:
        depth_m = np.full(shape[0] * shape[1], np.nan, dtype=np.float32)
        weaker_share = np.full(shape[0] * shape[1], np.nan, dtype=np.float32)
        depth_m[at], weaker_share[at] = weaker, share
        second = SecondReturns(depth_m.reshape(shape), weaker_share.reshape(shape))
    return MixedPixels(gate, replace(validity, usable_depth=usable), second, int(mixed.size - at.size), int(at.size))
