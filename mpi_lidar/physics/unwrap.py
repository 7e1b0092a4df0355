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
and the chosen tuple is the one whose range lies in [0, L). Its counts are right only if the range is on
the reported side of 0 = L too, so there the confidence also carries the share of the range's posterior on
that side: a pixel within noise of L (or of 0) is ambiguous between the two. Over a shorter window [0, R)
the pieces are those the window meets, and the range is the least-squares one, which noise may put
slightly outside [0, R).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from fractions import Fraction
from typing import TypeVar

import numpy as np
from numpy.typing import ArrayLike, NDArray

from mpi_lidar.errors import MpiLidarError
from mpi_lidar.physics.demod import unambiguous_range

# Posterior probability of the chosen wrap counts below which a pixel counts as ambiguous. If the noise model
# holds, the expected share of wrong counts among the pixels kept is the mean of 1 - confidence over them,
# below 0.1 % with this floor. At 12.5-31.25 MHz with sds in the ratio 2.52 : 1.70 : 1.28 : 1 the nearest
# wrong hypothesis costs 4.5 (1 m / sd_31.25)^2 more than the right one, so a pixel measured without noise
# falls below 0.999 only at sd_31.25 = 0.57 m, far beyond the 0.15 m of the faintest pixel correction accepts
# (docs/results/unwrapping.md); near 0 and the combined ambiguity it falls below within 3 range sds of the end.
MIN_UNWRAP_CONFIDENCE = 0.999
# Frequencies are compared on a grid of 1 mHz; a common divisor below 1 kHz (a combined ambiguity beyond
# 150 km) counts as none: no search over that many wrap counts is useful.
FREQUENCY_RESOLUTION_HZ = Fraction(1, 1000)
MIN_COMMON_DIVISOR_HZ = 1e3
MAX_HYPOTHESES = 1024  # pieces per pixel; beyond this a window is a mistake (units?) and is refused
CHUNK_ROWS = 8192  # rows swept at a time: working arrays of a few hundred KiB stay in the cache
# A window within this relative distance of the combined ambiguity is the whole circle.
PERIOD_RTOL = 1e-9

_Float = TypeVar("_Float", np.float32, np.float64)


@dataclass(frozen=True)
class Unwrapped:
    """Unwrapped depths of n pixels at F frequencies.

    depth_m : Each frequency's depth plus its wrap count times its unambiguous range, (n, F); NaN on rows
        with a non-finite input. [m]
    range_m : Inverse-variance weighted mean of the unwrapped depths, (n,); NaN on those rows. [m]
    confidence : Posterior probability of the chosen wrap counts against the other hypotheses under
        Gaussian noise of the given sds, and over the combined ambiguity of the range lying on the reported
        side of its end, (n,); 0 on rows with a non-finite input. [1]
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
    period = _period_m(frequencies_hz, c)
    if not math.isfinite(period):
        divisor = _common_divisor_hz(_frequency_fractions(frequencies_hz))
        raise MpiLidarError(
            f"the frequencies {np.asarray(frequencies_hz, dtype=np.float64).tolist()} Hz have no common divisor "
            f"of at least {MIN_COMMON_DIVISOR_HZ:g} Hz (found {float(divisor):g} Hz), so their depths do not "
            "repeat together within 150 km; give an explicit max_range_m")
    return period


def _period_m(frequencies_hz: ArrayLike, c: float) -> float:
    """The combined ambiguity, or infinity where the frequencies have no useful common divisor. [m]"""
    if not (math.isfinite(c) and c > 0):
        raise MpiLidarError(f"the speed of light must be a positive number of m/s, got {c}")
    divisor = _common_divisor_hz(_frequency_fractions(frequencies_hz))
    return float(c) / float(2 * divisor) if divisor >= MIN_COMMON_DIVISOR_HZ else math.inf


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

    Over the combined ambiguity L (the default) the result equals the exhaustive search over every wrap-count
    tuple whose weighted range lies in [0, L); over a shorter window [0, R), that over every tuple made of
    each frequency's nearest counts to some range in [0, R) (the module docstring says why). Depths are taken
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
    """What every row shares: the frequencies' ranges and which midpoints of each the window may hold."""

    ambiguity_m: NDArray[np.float64]  # (F,)
    period_m: float
    circle: bool  # the window is the whole combined ambiguity, whose two ends are one range
    label: NDArray[np.intp]  # (B,) the frequency of each midpoint column
    step_m: NDArray[np.float64]  # (B,) the column's whole number of its frequency's range above the first
    cycles: NDArray[np.int64]  # (F,) midpoints, and wrap counts, per combined ambiguity (on the circle)
    one_hot: NDArray[np.float64]  # (B, F) 1 where column b holds a midpoint of frequency f
    window_m: float
    window_end_m: float  # the window's end as the sort sees it: a midpoint at or past it starts no piece

    @staticmethod
    def make(ambiguity_m: NDArray[np.float64], window_m: float, period_m: float) -> _Plan:
        circle = window_m >= period_m * (1 - PERIOD_RTOL)
        # A circle of length L holds exactly L / A_f midpoints of frequency f; a window [0, R) at most ceil(R / A_f).
        span = period_m if circle else window_m
        count = (np.round(span / ambiguity_m) if circle else np.ceil(span / ambiguity_m)).astype(np.int64)
        if count.sum() + 1 > MAX_HYPOTHESES:
            raise MpiLidarError(
                f"unwrapping over {span:g} m takes {count.sum() + 1} hypotheses per pixel, more than "
                f"{MAX_HYPOTHESES}; give a shorter max_range_m")
        label = np.repeat(np.arange(ambiguity_m.size), count)
        step_m = np.concatenate([np.arange(c, dtype=np.float64) for c in count]) * ambiguity_m[label]
        one_hot = (label[:, None] == np.arange(ambiguity_m.size)).astype(np.float64)
        end = _split(_keys(np.full((1, label.size), span)), label.size)[0][0, 0]
        return _Plan(ambiguity_m, period_m, bool(circle), label, step_m, count, one_hot, span, float(end))


def _unwrap_chunk(depth: NDArray[np.float64], sigma: NDArray[np.float64], plan: _Plan, out: Unwrapped,
                  rows: slice) -> None:
    """Unwrap ``depth`` (m, F) and write the result into ``out`` at ``rows``."""
    finite = np.isfinite(_row_sum(depth) + _row_sum(sigma))  # NaN and inf propagate through a sum
    everywhere = bool(finite.all())
    if not everywhere:  # the rows with a missing value get a harmless stand-in, and NaN in the end
        depth, sigma = np.where(finite[:, None], depth, 0.0), np.where(finite[:, None], sigma, 1.0)
    wrapped = _wrap(depth, plan.ambiguity_m)
    weight = 1.0 / (sigma * sigma)
    total = _row_sum(weight)
    pieces = _sweep(wrapped, weight, total, plan)
    best = np.argmin(pieces.cost, axis=1)
    counts = pieces.start_counts + _passed(pieces, best, plan)
    fit = _fit(wrapped, weight, total, counts, plan)
    out.depth_m[rows], out.range_m[rows], out.chi2[rows], out.wrap_counts[rows] = fit
    out.confidence[rows] = _posterior(pieces.cost, best)
    if plan.circle:
        out.confidence[rows] *= 1.0 - _across_the_end(out.range_m[rows], total, plan.period_m)
    if not everywhere:
        missing = np.flatnonzero(~finite) + rows.start
        out.depth_m[missing], out.range_m[missing], out.chi2[missing] = np.nan, np.nan, np.nan
        out.confidence[missing], out.wrap_counts[missing] = 0.0, 0


def _wrap(depth: NDArray[np.float64], ambiguity_m: NDArray[np.float64]) -> NDArray[np.float64]:
    """Each depth modulo its frequency's range, in [0, A_f) (m, F): depth - floor(depth / A_f) A_f. [m]"""
    wrapped = depth - np.floor(depth * (1.0 / ambiguity_m)) * ambiguity_m  # np.mod's result, at half its cost
    below = wrapped < 0.0  # the quotient rounded up: one range too many taken off
    if below.any():
        wrapped[below] += np.broadcast_to(ambiguity_m, wrapped.shape)[below]
    wrapped[wrapped >= ambiguity_m] = 0.0  # a hair below a whole range is phase 2 pi: depth 0
    return wrapped


def _posterior(cost: NDArray[np.float64], best: NDArray[np.intp]) -> NDArray[np.float64]:
    """Posterior probability of the least-cost piece, 1 / sum_j exp(-(cost_j - cost_best) / 2), (m,)."""
    excess = cost - cost[np.arange(cost.shape[0]), best][:, None]
    # In float32, whose exponential is several times faster: a probability needs no more than its 7 digits.
    # Pieces more than 120 above the best (and empty ones) count as 120: 1e-26 of the best's weight.
    weight = np.minimum(excess, 120.0).astype(np.float32)
    weight *= np.float32(-0.5)
    np.exp(weight, out=weight)
    return 1.0 / _row_sum(weight).astype(np.float64)


def _across_the_end(range_m: NDArray[np.float64], total_weight: NDArray[np.float64],
                    period_m: float) -> NDArray[np.float64]:
    """Posterior share of each range across the nearer end of [0, L), where it reads as the other end. [1]

    On the circle a range a little below 0 is one a little below L: the same wrap counts modulo a period, but
    not the same counts or range. The chosen hypothesis's range is Gaussian about the weighted mean with sd
    1 / sqrt(sum w); the share of it past the nearer end, Phi(-distance / sd), has its counts one period off.
    """
    share = np.zeros_like(range_m)
    z = np.minimum(range_m, period_m - range_m) * np.sqrt(total_weight)
    near = np.flatnonzero(z < 9.0)  # Phi(-9) = 1e-19: only ranges within a few sds of an end need the tail
    if near.size:
        share[near] = [0.5 * math.erfc(v / math.sqrt(2.0)) for v in z[near]]
    return share


@dataclass(frozen=True)
class _Pieces:
    """Each row's pieces: their cost (m, P), inf where a piece is empty, and what rebuilds a piece's counts."""

    cost: NDArray[np.float64]
    start_counts: NDArray[np.int64]  # (m, F) each frequency's nearest count at range 0
    keys: NDArray[np.int64]  # (m, B) the midpoints with their columns, as the sort compared them
    sorted_keys: NDArray[np.int64]  # (m, B) ascending
    first: int  # midpoints passed to reach piece 0: 0 in a window (piece 0 starts at 0), 1 on the circle


def _sweep(wrapped: NDArray[np.float64], weight: NDArray[np.float64], total: NDArray[np.float64],
           plan: _Plan) -> _Pieces:
    """The cost of every piece of every row, from running weighted sums over the sorted midpoints."""
    a = plan.ambiguity_m
    start = np.floor(0.5 - wrapped / a)  # nearest count at range 0: 0, or -1 above half a range
    depth0 = wrapped + start * a  # the unwrapped depths of piece 0
    midpoints = (depth0 + 0.5 * a)[:, plan.label]  # first midpoints, in (0, A_f]: positive floats sort as their bits
    midpoints += plan.step_m
    if not plan.circle:
        np.minimum(midpoints, plan.window_m, out=midpoints)  # the pieces that start at or past the end are empty
    keys = _keys(midpoints)
    sorted_keys = np.sort(keys, axis=1)
    ordered, column = _split(sorted_keys, plan.label.size)
    # Piece 0 of a window starts at range 0, before any midpoint, and piece p at the p-th midpoint. On the
    # circle piece p starts at the (p + 1)-th midpoint, and the last one runs on to the first plus a period.
    first = 1 if plan.circle else 0
    sums = np.empty((2, wrapped.shape[0], plan.label.size + 1 - first))
    # Passing the midpoint b of frequency f raises its count by one: d_f goes from b - A_f/2 to b + A_f/2,
    # which adds w_f A_f to sum w d and 2 b w_f A_f to sum w d^2.
    step = np.take_along_axis((weight * a)[:, plan.label], column, axis=1)
    sums[0, :, 1 - first:] = step
    np.multiply(ordered, 2.0 * step, out=sums[1, :, 1 - first:])
    if first:
        sums[0, :, 0] += _row_sum(weight * depth0)
        sums[1, :, 0] += _row_sum(weight * depth0 * depth0)
    else:
        sums[0, :, 0] = _row_sum(weight * depth0)
        sums[1, :, 0] = _row_sum(weight * depth0 * depth0)
    for p in range(1, sums.shape[2]):  # a running sum, column by column: faster than cumsum along short rows
        sums[:, :, p] += sums[:, :, p - 1]
    # cost = sum w d^2 - (sum w d)^2 / sum w, in place
    cost = sums[1]
    np.square(sums[0], out=sums[0])
    sums[0] /= total[:, None]
    cost -= sums[0]
    np.maximum(cost, 0.0, out=cost)
    _mark_empty(cost, ordered, plan)
    return _Pieces(cost, start.astype(np.int64), keys, sorted_keys, first)


def _mark_empty(cost: NDArray[np.float64], ordered: NDArray[np.float64], plan: _Plan) -> None:
    """Set the cost of pieces of no width to inf: between two equal midpoints, or past the window's end."""
    if plan.circle:
        cost[:, :-1][ordered[:, 1:] <= ordered[:, :-1]] = np.inf
    else:
        cost[:, 1:-1][ordered[:, 1:] <= ordered[:, :-1]] = np.inf
        cost[:, 1:][ordered >= plan.window_end_m] = np.inf


def _row_sum(x: NDArray[_Float]) -> NDArray[_Float]:
    """Sum over the columns of ``x`` (m, k), column by column: faster than a reduction along short rows."""
    total = x[:, 0].copy()
    for column in range(1, x.shape[1]):
        total += x[:, column]
    return total


def _column_mask(columns: int) -> np.int64:
    """The low bits of a sort key that hold a column index below ``columns``."""
    return np.int64(2 ** max(1, (columns - 1).bit_length()) - 1)


def _keys(midpoints: NDArray[np.float64]) -> NDArray[np.int64]:
    """Each positive midpoint [m] with its column index in the low bits of its float, as an integer.

    The bits of a positive float order as its value does, so one sort of these integers orders the midpoints
    and carries their columns along, at half the cost of an argsort and a gather. Midpoints that differ by
    less than 2^bits units in the last place (16 units, 4e-15 relative, for 14 columns) count as equal.
    """
    low = _column_mask(midpoints.shape[1])
    return (midpoints.view(np.int64) & ~low) | np.arange(midpoints.shape[1], dtype=np.int64)


def _split(keys: NDArray[np.int64], columns: int) -> tuple[NDArray[np.float64], NDArray[np.int64]]:
    """The midpoints [m], to within the bits the column took, and the columns of keys from :func:`_keys`."""
    low = _column_mask(columns)
    return (keys & ~low).view(np.float64), keys & low


def _passed(pieces: _Pieces, best: NDArray[np.intp], plan: _Plan) -> NDArray[np.int64]:
    """How many midpoints of each frequency the sweep passed to reach the chosen piece, (m, F)."""
    passed = best + pieces.first
    last = pieces.sorted_keys[np.arange(best.size), np.maximum(passed - 1, 0)]
    below = (pieces.keys <= last[:, None]) & (passed[:, None] > 0)
    return np.rint(below.astype(np.float64) @ plan.one_hot).astype(np.int64)


def _fit(wrapped: NDArray[np.float64], weight: NDArray[np.float64], total: NDArray[np.float64],
         counts: NDArray[np.int64], plan: _Plan,
         ) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64], NDArray[np.int64]]:
    """Unwrapped depths, weighted range and chi2 of the chosen counts, recomputed exactly from the tuple."""
    a = plan.ambiguity_m
    depth = wrapped + counts * a
    range_m = _row_sum(weight * depth) / total
    if plan.circle:
        # The same hypothesis a whole number of periods away: the one whose range lies in [0, L).
        turns = np.floor(range_m / plan.period_m).astype(np.int64)
        moved = np.flatnonzero(turns)
        if moved.size:
            counts[moved] -= turns[moved, None] * plan.cycles
            depth[moved] = wrapped[moved] + counts[moved] * a
            range_m[moved] = _row_sum(weight[moved] * depth[moved]) / total[moved]
    chi2 = _row_sum(weight * (depth - range_m[:, None]) ** 2)
    return depth, range_m, chi2, counts
