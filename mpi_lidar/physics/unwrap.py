"""Multi-frequency phase unwrapping: the wrap counts under which the depths of all frequencies agree best.

Frequency f measures its depth modulo its unambiguous range A_f = c / (2 f). A wrap-count hypothesis
k = (k_f) unwraps the wrapped depths m_f to d_f = m_f + k_f A_f. Under independent Gaussian noise of sd
sigma_f its log-likelihood, the range integrated out under a flat prior, is -cost(k) / 2 plus a constant,
with the weighted least-squares cost

    cost(k) = sum_f (d_f - r_k)^2 / sigma_f^2,    r_k = the inverse-variance weighted mean of the d_f,

so the best hypothesis is the one of least cost and its posterior probability against the others is
1 / sum_j exp(-(cost_j - cost_best) / 2): the noise-weighted search over wrap counts of the multi-frequency
time-of-flight literature, here exhaustive and exact.

The search. For a fixed range r each frequency's best count is its nearest, k_f(r) = floor((r - m_f) / A_f + 1/2),
and min_r sum_f min_k (m_f + k A_f - r)^2 / sigma_f^2 bounds every tuple's cost from below, so the best tuple
is one of the k(r). These change only where r crosses a midpoint m_f + (j + 1/2) A_f of some frequency's
lattice, which cut the ranges into a few pieces: sum_f R / A_f of them over ranges [0, R), 14 over the 24 m
combined ambiguity of 12.5, 18.75, 25 and 31.25 MHz. The pieces are the hypotheses. Sorting each pixel's
midpoints and sweeping them with running weighted sums gives the cost of every piece in O(pieces) per pixel.

The combined ambiguity L = c / (2 gcd(f)) is the period of the whole pattern: ranges r and r + L give the
same wrapped depths at every frequency. Over ranges [0, L) (the default) the pieces are those of a circle,
and the chosen tuple is the one whose range lies in [0, L). Over a shorter window [0, R) the pieces are those
the window meets, and the range is the least-squares one, which noise may put slightly outside [0, R).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from fractions import Fraction

import numpy as np
from numpy.typing import ArrayLike, NDArray

from mpi_lidar.errors import MpiLidarError
from mpi_lidar.physics.demod import unambiguous_range

# Posterior probability of the chosen wrap counts below which a pixel counts as ambiguous. If the noise model
# holds, the expected share of wrong counts among the pixels kept is the mean of 1 - confidence over them,
# so a floor of 0.999 keeps it below 0.1 %; at the default frequencies a correctly unwrapped pixel falls
# below it only when its noise reaches about a sixth of the 31.25 MHz range (docs/results/unwrapping.md).
MIN_UNWRAP_CONFIDENCE = 0.999
# Frequencies are compared on a grid of 1 mHz; a common divisor below 1 kHz (a combined ambiguity beyond
# 150 km) counts as none: no search over that many wrap counts is useful.
FREQUENCY_RESOLUTION_HZ = Fraction(1, 1000)
MIN_COMMON_DIVISOR_HZ = 1e3
MAX_HYPOTHESES = 1024  # pieces per pixel; beyond this a window is a mistake (units?) and is refused
CHUNK_ROWS = 32_768  # rows swept at a time: a few MiB of working arrays, which stay in cache
# A window within this relative distance of the combined ambiguity is the whole circle.
PERIOD_RTOL = 1e-9


@dataclass(frozen=True)
class Unwrapped:
    """Unwrapped depths of n pixels at F frequencies.

    depth_m : Each frequency's depth plus its wrap count times its unambiguous range, (n, F); NaN on rows
        with a non-finite input. [m]
    range_m : Inverse-variance weighted mean of the unwrapped depths, (n,); NaN on those rows. [m]
    confidence : Posterior probability of the chosen wrap counts against the other hypotheses under
        Gaussian noise of the given sds, (n,); 0 on rows with a non-finite input. [1]
    wrap_counts : The chosen wrap count of each frequency, (n, F), int16; 0 on rows with a non-finite input.
    chi2 : Weighted squared residual of the chosen hypothesis, sum_f ((depth_f - range) / sigma_f)^2, (n,):
        chi-square with F - 1 degrees of freedom when the noise model holds; NaN on those rows. [1]
    """

    depth_m: NDArray[np.float64]
    range_m: NDArray[np.float64]
    confidence: NDArray[np.float64]
    wrap_counts: NDArray[np.int16]
    chi2: NDArray[np.float64]


def _frequency_fractions(frequencies_hz: ArrayLike) -> list[Fraction]:
    freqs = np.asarray(frequencies_hz, dtype=np.float64)
    if freqs.ndim != 1 or freqs.size == 0 or not np.all(np.isfinite(freqs)) or np.any(freqs <= 0):
        raise MpiLidarError(f"expected a 1-D array of positive modulation frequencies, got {freqs.tolist()} Hz")
    # The nearest fraction with a denominator of at most 1000 lies within 1 mHz of each value: float noise
    # from unit conversions (18.75 * 1e6) goes, and a frequency of 10/3 MHz stays 10/3 MHz.
    return [Fraction(float(f)).limit_denominator(int(1 / FREQUENCY_RESOLUTION_HZ)) for f in freqs]


def _common_divisor_hz(fractions: list[Fraction]) -> Fraction:
    divisor = Fraction(0)
    for f in fractions:
        divisor = Fraction(math.gcd(divisor.numerator * f.denominator, f.numerator * divisor.denominator),
                           divisor.denominator * f.denominator)
    return divisor


def combined_ambiguity_m(frequencies_hz: ArrayLike, c: float) -> float:
    """Range after which the wrapped depths of all frequencies repeat together, c / (2 gcd(f)). [m]

    24 m for 12.5, 18.75, 25 and 31.25 MHz (gcd 6.25 MHz) with c = 3e8 m/s, 30 m for 10 and 15 MHz. The
    frequencies are taken to 1 mHz; a set whose greatest common divisor is below 1 kHz has no useful combined
    ambiguity (beyond 150 km) and raises :class:`MpiLidarError`: unwrap such a set over an explicit
    ``max_range_m``.

    Parameters
    ----------
    frequencies_hz : Modulation frequencies (F,). [Hz]
    c : Speed of light. [m/s]
    """
    divisor = _common_divisor_hz(_frequency_fractions(frequencies_hz))
    if divisor < MIN_COMMON_DIVISOR_HZ:
        raise MpiLidarError(
            f"the frequencies {np.asarray(frequencies_hz, dtype=np.float64).tolist()} Hz have no common divisor "
            f"of at least {MIN_COMMON_DIVISOR_HZ:g} Hz (found {float(divisor):g} Hz), so their depths do not "
            "repeat together within 150 km; give an explicit max_range_m")
    return float(c / (2 * divisor))


def _period_m(frequencies_hz: ArrayLike, c: float) -> float:
    """The combined ambiguity, or infinity where the frequencies have no useful common divisor. [m]"""
    try:
        return combined_ambiguity_m(frequencies_hz, c)
    except MpiLidarError:
        return math.inf


def _window_m(max_range_m: float | None, period_m: float, frequencies_hz: ArrayLike, c: float) -> float:
    if max_range_m is None:
        return combined_ambiguity_m(frequencies_hz, c)  # raises where the frequencies have no useful one
    if not (math.isfinite(max_range_m) and max_range_m > 0):
        raise MpiLidarError(f"max_range_m must be a positive distance, got {max_range_m}")
    if max_range_m > period_m * (1 + PERIOD_RTOL):
        raise MpiLidarError(
            f"max_range_m = {max_range_m:g} m exceeds the frequencies' combined ambiguity of {period_m:g} m: "
            "ranges that far apart give the same depths at every frequency, so no unwrapping can tell them apart")
    return min(max_range_m, period_m)


def unwrap_depths(depth_m: ArrayLike, sigma_m: ArrayLike, frequencies_hz: ArrayLike, c: float,
                  max_range_m: float | None = None) -> Unwrapped:
    """The wrap counts of each pixel whose unwrapped depths agree best, weighted by their noise.

    Equals the exhaustive search over all wrap-count tuples whose weighted range lies in [0, max_range_m)
    (the module docstring says how, and what happens at the ends of a shorter window). Depths are taken
    modulo each frequency's unambiguous range first, so wrapped and unwrapped inputs give the same result.
    A row with a non-finite depth or sd gives NaN depths, range and chi2, wrap counts 0 and confidence 0.

    Parameters
    ----------
    depth_m : Measured depth per pixel and frequency (n, F), wrapped or not. [m]
    sigma_m : Sd of each measured depth (n, F), positive. [m]
    frequencies_hz : Modulation frequencies (F,). [Hz]
    c : Speed of light. [m/s]
    max_range_m : Farthest range searched; default and at most the combined ambiguity
        (:func:`combined_ambiguity_m`). [m]
    """
    freqs = np.asarray(frequencies_hz, dtype=np.float64)
    period = _period_m(freqs, c)
    window = _window_m(max_range_m, period, freqs, c)
    depth, sigma = _rows(depth_m, sigma_m, freqs)
    ambiguity = unambiguous_range(freqs, c)
    plan = _Plan.make(ambiguity, window, period)
    n = depth.shape[0]
    out = Unwrapped(np.empty((n, freqs.size)), np.empty(n), np.empty(n), np.empty((n, freqs.size), np.int16),
                    np.empty(n))
    for start in range(0, n, CHUNK_ROWS):
        rows = slice(start, start + CHUNK_ROWS)
        _unwrap_chunk(depth[rows], sigma[rows], plan, out, rows)
    return out


def ambiguous(unwrapped: Unwrapped, min_confidence: float = MIN_UNWRAP_CONFIDENCE) -> NDArray[np.bool_]:
    """Pixels whose wrap counts are not certain enough to trust, (n,): confidence below ``min_confidence``.

    Rows with a non-finite input have confidence 0 and are always ambiguous. :data:`MIN_UNWRAP_CONFIDENCE`
    says why 0.999. A chi2 far above F - 1 (frequencies that disagree beyond their noise) is a separate
    question, left to the caller.

    Parameters
    ----------
    unwrapped : The result of :func:`unwrap_depths`.
    min_confidence : Posterior probability of the chosen wrap counts below which a pixel is ambiguous. [1]
    """
    return ~(unwrapped.confidence >= min_confidence)


def _rows(depth_m: ArrayLike, sigma_m: ArrayLike,
          freqs: NDArray[np.float64]) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    depth = np.asarray(depth_m, dtype=np.float64)
    sigma = np.asarray(sigma_m, dtype=np.float64)
    expected = (depth.shape[0] if depth.ndim == 2 else -1, freqs.size)
    if depth.ndim != 2 or depth.shape != expected or sigma.shape != depth.shape:
        raise MpiLidarError(f"expected depths and sds of shape (n, {freqs.size}), got {depth.shape} and {sigma.shape}")
    if np.any(sigma <= 0):
        raise MpiLidarError("depth sds must be positive (NaN marks a missing value)")
    return depth, sigma


@dataclass(frozen=True)
class _Plan:
    """What every row shares: the frequencies' ranges and how many midpoints of each the window holds."""

    ambiguity_m: NDArray[np.float64]  # (F,)
    window_m: float
    period_m: float
    circle: bool  # the window is the whole combined ambiguity: its two ends are one range
    label: NDArray[np.intp]  # (B,) the frequency of each midpoint column
    step: NDArray[np.float64]  # (B,) the column's multiple j of its frequency's range
    cycles: NDArray[np.int64]  # (F,) wrap counts per period (circle only)
    one_hot: NDArray[np.float64]  # (B, F) which frequency each midpoint column belongs to

    @staticmethod
    def make(ambiguity_m: NDArray[np.float64], window_m: float, period_m: float) -> _Plan:
        circle = window_m >= period_m * (1 - PERIOD_RTOL)
        # On the circle each frequency has exactly L / A_f midpoints per period; in a window at most ceil(R / A_f).
        span = period_m if circle else window_m
        per_frequency = np.round(span / ambiguity_m) if circle else np.ceil(span / ambiguity_m)
        count = per_frequency.astype(np.int64)
        if count.sum() + 1 > MAX_HYPOTHESES:
            raise MpiLidarError(
                f"unwrapping over {span:g} m takes {count.sum() + 1} hypotheses per pixel, more than "
                f"{MAX_HYPOTHESES}; give a shorter max_range_m")
        label = np.repeat(np.arange(ambiguity_m.size), count)
        step = np.concatenate([np.arange(c, dtype=np.float64) for c in count])
        one_hot = (label[:, None] == np.arange(ambiguity_m.size)).astype(np.float64)
        return _Plan(ambiguity_m, span, period_m, circle, label, step, count, one_hot)


def _unwrap_chunk(depth: NDArray[np.float64], sigma: NDArray[np.float64], plan: _Plan, out: Unwrapped,
                  rows: slice) -> None:
    """Unwrap ``depth`` (m, F) and write the result into ``out`` at ``rows``."""
    finite = np.isfinite(depth).all(axis=1) & np.isfinite(sigma).all(axis=1)
    a = plan.ambiguity_m
    wrapped = np.where(finite[:, None], np.mod(np.where(finite[:, None], depth, 0.0), a), 0.0)
    wrapped = np.where(wrapped >= a, 0.0, wrapped)  # np.mod(-tiny, A) rounds to exactly A; that depth is 0
    weight = np.where(finite[:, None], 1.0 / np.where(finite[:, None], sigma, 1.0) ** 2, 1.0)
    pieces = _sweep(wrapped, weight, plan)
    best = np.argmin(pieces.cost, axis=1)
    best_cost = np.take_along_axis(pieces.cost, best[:, None], axis=1)
    confidence = 1.0 / np.exp(-0.5 * (pieces.cost - best_cost)).sum(axis=1)
    counts = pieces.start_counts + _passed(pieces, best, plan)
    unwrapped, range_m, chi2, counts = _fit(wrapped, weight, counts, plan)
    out.depth_m[rows] = np.where(finite[:, None], unwrapped, np.nan)
    out.range_m[rows] = np.where(finite, range_m, np.nan)
    out.chi2[rows] = np.where(finite, chi2, np.nan)
    out.confidence[rows] = np.where(finite, confidence, 0.0)
    out.wrap_counts[rows] = np.where(finite[:, None], counts, 0)


@dataclass(frozen=True)
class _Pieces:
    """Each row's pieces of the window: cost (m, P) (inf where a piece is empty), and what rebuilds a tuple."""

    cost: NDArray[np.float64]
    start_counts: NDArray[np.int64]  # (m, F) each frequency's nearest count at range 0
    midpoints: NDArray[np.float64]  # (m, B) in column order
    sorted_midpoints: NDArray[np.float64]  # (m, B) ascending
    first: int  # midpoints passed before piece 0: 0 in a window (piece 0 starts at 0), 1 on the circle


def _sweep(wrapped: NDArray[np.float64], weight: NDArray[np.float64], plan: _Plan) -> _Pieces:
    """The cost of every piece of every row, from running sums over the sorted midpoints."""
    a = plan.ambiguity_m
    start = np.floor(0.5 - wrapped / a)  # nearest count at range 0: 0, or -1 above half a range
    first_midpoint = wrapped + (start + 0.5) * a  # in (0, A_f]
    midpoints = first_midpoint[:, plan.label] + plan.step * a[plan.label]
    if not plan.circle:
        midpoints = np.minimum(midpoints, plan.window_m)  # beyond the window: pieces that start there are empty
    order = np.argsort(midpoints, axis=1)
    ordered = np.take_along_axis(midpoints, order, axis=1)
    # Passing the midpoint b of frequency f raises its count by one: d_f goes from b - A_f/2 to b + A_f/2.
    weighted_step = np.take_along_axis((weight * a)[:, plan.label], order, axis=1)
    total = weight.sum(axis=1, keepdims=True)
    depth0 = wrapped + start * a
    sum1 = np.cumsum(weighted_step, axis=1) + (weight * depth0).sum(axis=1, keepdims=True)
    sum2 = np.cumsum(2.0 * ordered * weighted_step, axis=1) + (weight * depth0**2).sum(axis=1, keepdims=True)
    if plan.circle:
        # Piece p starts at the p-th midpoint and ends at the next (the last at the first plus a period).
        ends = np.concatenate([ordered[:, 1:], ordered[:, :1] + plan.period_m], axis=1)
        empty = ends <= ordered
        first = 1
    else:
        # Piece 0 starts at range 0; piece p >= 1 at the p-th midpoint, if that lies inside the window.
        sum1 = np.concatenate([(weight * depth0).sum(axis=1, keepdims=True), sum1], axis=1)
        sum2 = np.concatenate([(weight * depth0**2).sum(axis=1, keepdims=True), sum2], axis=1)
        ends = np.concatenate([ordered, np.full_like(ordered[:, :1], plan.window_m)], axis=1)
        starts = np.concatenate([np.zeros_like(ordered[:, :1]), ordered], axis=1)
        empty = ends <= starts
        first = 0
    cost = np.maximum(sum2 - sum1**2 / total, 0.0)
    return _Pieces(np.where(empty, np.inf, cost), start.astype(np.int64), midpoints, ordered, first)


def _passed(pieces: _Pieces, best: NDArray[np.intp], plan: _Plan) -> NDArray[np.int64]:
    """How many midpoints of each frequency the sweep passed to reach the chosen piece, (m, F)."""
    passed = best + pieces.first
    last = np.take_along_axis(pieces.sorted_midpoints, np.maximum(passed - 1, 0)[:, None], axis=1)
    # A chosen piece is never empty, so the midpoints passed are exactly those up to the last one passed.
    below = (pieces.midpoints <= last) & (passed[:, None] > 0)
    return np.rint(below.astype(np.float64) @ plan.one_hot).astype(np.int64)


def _fit(wrapped: NDArray[np.float64], weight: NDArray[np.float64], counts: NDArray[np.int64],
         plan: _Plan) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64], NDArray[np.int64]]:
    """Unwrapped depths, weighted range and chi2 of the chosen counts, recomputed exactly from the tuple."""
    a = plan.ambiguity_m
    depth = wrapped + counts * a
    range_m = (weight * depth).sum(axis=1) / weight.sum(axis=1)
    if plan.circle:
        # The same hypothesis a whole number of periods away: the one whose range lies in [0, L).
        turns = np.floor(range_m / plan.period_m)
        counts = counts - turns[:, None].astype(np.int64) * plan.cycles
        depth = wrapped + counts * a
        range_m = (weight * depth).sum(axis=1) / weight.sum(axis=1)
    chi2 = (weight * (depth - range_m[:, None]) ** 2).sum(axis=1)
    return depth, range_m, chi2, counts
