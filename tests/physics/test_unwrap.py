"""Multi-frequency phase unwrapping: closed-form ranges, wrap boundaries, the exhaustive search, confidence."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import assume, given, settings
from hypothesis import strategies as st

from mpi_lidar.config import PAPER_FREQUENCIES_HZ, Config, SensorConfig
from mpi_lidar.errors import MpiLidarError
from mpi_lidar.physics import unwrap
from mpi_lidar.physics.moments import MomentSensor
from mpi_lidar.physics.noise import depth_noise_m
from mpi_lidar.physics.unwrap import (
    MIN_UNWRAP_CONFIDENCE,
    Unwrapped,
    ambiguous,
    combined_ambiguity_m,
    unwrap_depths,
)

pytestmark = pytest.mark.unit

C = 3.0e8
FREQS = np.array(PAPER_FREQUENCIES_HZ)
RANGES = C / (2 * FREQS)  # 12, 8, 6, 4.8 m
SD_RATIOS = np.array([2.52, 1.70, 1.28, 1.0])  # depth sd per frequency at equal amplitude, over the 31.25 MHz one
FREQUENCY_SETS = [PAPER_FREQUENCIES_HZ, (10e6, 15e6), (12.5e6, 31.25e6), (20e6, 25e6, 30e6)]


def noisy(true_m: np.ndarray, sigma_m: np.ndarray, rng: np.random.Generator,
          freqs: np.ndarray = FREQS) -> np.ndarray:
    """Wrapped depths (n, F) of true ranges (n,) with Gaussian noise of sds (n, F). [m]"""
    return np.mod(true_m[:, None] + sigma_m * rng.standard_normal(sigma_m.shape), C / (2 * freqs))


def wrapped(depth_m: np.ndarray, freqs: np.ndarray) -> np.ndarray:
    a = C / (2 * freqs)
    x = np.mod(depth_m, a)
    return np.where(x >= a, 0.0, x)


def all_tuples(freqs: np.ndarray, span_m: float) -> np.ndarray:
    """Every wrap-count tuple with each count in [-2, ceil(span / A_f) + 1], shape (T, F)."""
    a = C / (2 * freqs)
    axes = [np.arange(-2, int(np.ceil(span_m / a_f - 1e-9)) + 2) for a_f in a]
    return np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, freqs.size)


def tuple_fits(x: np.ndarray, sigma: np.ndarray, counts: np.ndarray,
               freqs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Weighted range (T,) and cost (T,) of each tuple of counts (T, F) for one row of wrapped depths (F,)."""
    w = 1.0 / sigma**2
    d = x + counts * (C / (2 * freqs))
    r = (w * d).sum(axis=1) / w.sum()
    return r, (w * (d - r[:, None]) ** 2).sum(axis=1)


def consistent(x: np.ndarray, counts: np.ndarray, freqs: np.ndarray, window_m: float) -> np.ndarray:
    """Tuples (T, F) that are every frequency's nearest counts for some range in [0, window_m) (T,)."""
    a = C / (2 * freqs)
    low = np.maximum((x + (counts - 0.5) * a).max(axis=1), 0.0)
    high = np.minimum((x + (counts + 0.5) * a).min(axis=1), window_m)
    return high > low


def midpoint_gap(x: np.ndarray, freqs: np.ndarray, span_m: float) -> float:
    """Smallest distance between two lattice midpoints of different frequencies within [-1, span + 1] m."""
    a = C / (2 * freqs)
    points = np.sort(np.concatenate([x[f] + (np.arange(-2, span_m / a[f] + 2) + 0.5) * a[f]
                                     for f in range(freqs.size)]))
    points = points[(points > -1) & (points < span_m + 1)]
    return float(np.diff(points).min()) if points.size > 1 else np.inf


def posterior(cost: np.ndarray) -> float:
    return float(1.0 / np.exp(-0.5 * (cost - cost.min())).sum())


def same_side(range_m: float, sigma_m: np.ndarray, period_m: float) -> float:
    """Share of a range's Gaussian posterior (sd 1 / sqrt(sum 1 / sigma^2)) on its side of the ends of the circle."""
    z = min(range_m, period_m - range_m) * math.sqrt((1 / sigma_m**2).sum())
    return 1 - 0.5 * math.erfc(z / math.sqrt(2))


@st.composite
def noisy_rows(draw, window: bool = False):
    """One row: frequencies, depths, sds (near wrap points, the ends of the range, or anywhere; sometimes
    depths that fit no range at all) and the window searched."""
    freqs = np.array(draw(st.sampled_from(FREQUENCY_SETS)))
    a = C / (2 * freqs)
    period = combined_ambiguity_m(freqs, C)
    span = draw(st.floats(0.5, 0.999 * period)) if window else period
    where = draw(st.sampled_from(["anywhere", "wrap", "ends"]))
    if where == "anywhere":
        true = draw(st.floats(0.0, span))
    elif where == "wrap":
        f = draw(st.integers(0, freqs.size - 1))
        true = draw(st.integers(0, int(span / a[f]))) * a[f] + draw(st.floats(-1e-3, 1e-3))
    else:
        true = draw(st.sampled_from([0.0, span])) + draw(st.floats(-1e-3, 1e-3))
    scale = draw(st.floats(1e-3, 3.0))
    sigma = scale * freqs.max() / freqs * np.array([draw(st.floats(0.5, 2.0)) for _ in freqs])
    if draw(st.booleans()):
        depth = true + sigma * np.array([draw(st.floats(-3.0, 3.0)) for _ in freqs])
    else:
        depth = np.array([draw(st.floats(0.0, a_f)) for a_f in a])  # any wrapped depths at all
    return freqs, depth, sigma, span


# --- combined ambiguity ---------------------------------------------------------------------------------------

@pytest.mark.parametrize(("frequencies_hz", "c", "expected_m"), [
    (PAPER_FREQUENCIES_HZ, C, 24.0),  # gcd 6.25 MHz
    (PAPER_FREQUENCIES_HZ, 299_792_458.0, 299_792_458.0 / (2 * 6.25e6)),  # 23.98 m
    ((10e6, 15e6), C, 30.0),  # gcd 5 MHz
    ((1e7 / 3, 1e7), C, 45.0),  # gcd 10/3 MHz: fractions, not a decimal grid
    ((31.25e6,), C, 4.8),  # one frequency: its own range
])
def test_combined_ambiguity_m__is_c_over_twice_the_greatest_common_divisor(frequencies_hz, c, expected_m):
    assert combined_ambiguity_m(frequencies_hz, c) == pytest.approx(expected_m, rel=1e-12)


def test_combined_ambiguity_m__float_noise_of_unit_conversions_is_ignored():
    freqs = np.array([12.5, 18.75, 25.0, 31.25]) * 1e6 * (1 + np.array([1e-15, -2e-15, 0.0, 3e-15]))
    assert combined_ambiguity_m(freqs, C) == pytest.approx(24.0, rel=1e-12)


@pytest.mark.parametrize("frequencies_hz", [(12.5e6, 12.5e6 + 0.5), (12.5e6, 18.7501234e6), (10e6, 10e6 + 999.0)])
def test_combined_ambiguity_m__no_common_divisor_of_a_kilohertz_raises(frequencies_hz):
    with pytest.raises(MpiLidarError, match="no common divisor of at least 1000 Hz"):
        combined_ambiguity_m(frequencies_hz, C)


@pytest.mark.parametrize("frequencies_hz", [(), (12.5e6, -1.0), (np.nan,), ((1e6, 2e6),)])
def test_combined_ambiguity_m__refuses_what_is_not_a_set_of_frequencies(frequencies_hz):
    with pytest.raises(MpiLidarError, match="positive modulation frequencies"):
        combined_ambiguity_m(frequencies_hz, C)


# --- closed-form cases ----------------------------------------------------------------------------------------

@pytest.mark.parametrize("true_m", [0.0005, 0.3, 4.79, 4.81, 6.0, 11.99, 12.01, 23.9, 23.9995])
def test_unwrap_depths__known_ranges_with_tiny_noise_unwrap_exactly(true_m):
    rng = np.random.default_rng(int(true_m * 1e4))
    sigma = np.full((50, 4), 1e-4)
    noise = 1e-5 * rng.standard_normal((50, 4))
    unwrapped = unwrap_depths(np.mod(true_m + noise, RANGES), sigma, FREQS, C)
    np.testing.assert_array_equal(unwrapped.wrap_counts, np.floor((true_m + noise) / RANGES))
    np.testing.assert_allclose(unwrapped.depth_m, true_m + noise, rtol=0, atol=1e-12)
    np.testing.assert_allclose(unwrapped.range_m, true_m, rtol=0, atol=5e-5)
    assert np.all(unwrapped.confidence == 1.0) and not ambiguous(unwrapped).any()
    assert np.all(unwrapped.chi2 < 0.2)  # (1e-5 / 1e-4)^2 per frequency, 3 degrees of freedom
    assert unwrapped.wrap_counts.dtype == np.int16


@pytest.mark.parametrize(("true_m", "top_measured_m", "top_count", "top_unwrapped_m"), [
    (4.799, 0.001, 1, 4.801),  # just below the 31.25 MHz wrap, measured just past it
    (4.801, 4.799, 0, 4.799),  # just past it, measured just below it
    (9.599, 0.001, 2, 9.601),  # its second wrap
    (23.999, 0.001, 5, 24.001),  # its last wrap, at the end of the combined ambiguity
])
def test_unwrap_depths__a_depth_measured_across_its_wrap_point_unwraps_to_the_near_side(
        true_m, top_measured_m, top_count, top_unwrapped_m):
    depth = np.append(np.mod(true_m, RANGES[:3]), top_measured_m)[None, :]
    unwrapped = unwrap_depths(depth, np.full((1, 4), 2e-3), FREQS, C)
    assert unwrapped.wrap_counts[0, 3] == top_count
    assert unwrapped.depth_m[0, 3] == pytest.approx(top_unwrapped_m, abs=1e-12)
    np.testing.assert_allclose(unwrapped.depth_m[0, :3], true_m, rtol=0, atol=1e-12)
    # equal sds: the range is the plain mean of the unwrapped depths
    assert unwrapped.range_m[0] == pytest.approx((3 * true_m + top_unwrapped_m) / 4, abs=1e-12)
    assert unwrapped.chi2[0] == pytest.approx(0.75 * (top_unwrapped_m - true_m) ** 2 / 2e-3**2, rel=1e-6)
    # 24 m and 0 are one range on the circle: a range 0.5 m away from 24 m, with sd 1 mm, lies past it with
    # probability Phi(-0.5), where its counts would be (0, 0, 0, 0) and its range 0.5 mm
    expected = same_side(unwrapped.range_m[0], np.full(4, 2e-3), 24.0)
    assert unwrapped.confidence[0] == pytest.approx(expected, rel=1e-12)
    assert expected == 1.0 or expected == pytest.approx(1 - 0.5 * math.erfc(0.5 / math.sqrt(2)))


@pytest.mark.parametrize("true_m", [4.8, 6.0, 12.0, 14.4, 16.0, 18.0, 19.2])
def test_unwrap_depths__phase_zero_and_two_pi_are_the_same_depth(true_m):
    # at a multiple of a frequency's range its depth may be reported as 0 or as the whole range
    at_zero = np.mod(true_m, RANGES)
    wraps = np.isclose(at_zero, 0.0, atol=1e-12) | np.isclose(at_zero, RANGES, atol=1e-12)
    at_zero[wraps] = 0.0
    at_full = np.where(wraps, RANGES, at_zero)
    sigma = np.full((1, 4), 1e-3)
    low = unwrap_depths(at_zero[None, :], sigma, FREQS, C)
    high = unwrap_depths(at_full[None, :], sigma, FREQS, C)
    assert wraps.any()
    for result in (low, high):
        assert result.range_m[0] == pytest.approx(true_m, abs=1e-12)
        assert result.confidence[0] == 1.0
    np.testing.assert_array_equal(low.wrap_counts, high.wrap_counts)


def test_unwrap_depths__already_unwrapped_inputs_give_the_same_result():
    rng = np.random.default_rng(3)
    true = rng.uniform(0.05, 23.95, 2000)
    sigma = rng.uniform(0.001, 0.1, (2000, 1)) * SD_RATIOS
    unwrapped_input = true[:, None] + sigma * rng.standard_normal((2000, 4))
    from_wrapped = unwrap_depths(np.mod(unwrapped_input, RANGES), sigma, FREQS, C)
    from_unwrapped = unwrap_depths(unwrapped_input, sigma, FREQS, C)
    np.testing.assert_array_equal(from_unwrapped.wrap_counts, from_wrapped.wrap_counts)
    np.testing.assert_allclose(from_unwrapped.depth_m, unwrapped_input, rtol=0, atol=1e-12)
    np.testing.assert_allclose(from_unwrapped.range_m, from_wrapped.range_m, rtol=0, atol=1e-12)
    np.testing.assert_allclose(from_unwrapped.confidence, from_wrapped.confidence, rtol=1e-9, atol=0)


def test_unwrap_depths__two_frequencies_unwrap_over_their_combined_30_m():
    freqs = np.array([10e6, 15e6])  # ranges 15 and 10 m
    true = np.linspace(0.05, 29.95, 600)
    sigma = np.tile([3e-3, 2e-3], (600, 1))
    unwrapped = unwrap_depths(noisy(true, sigma, np.random.default_rng(4), freqs), sigma, freqs, C)
    assert combined_ambiguity_m(freqs, C) == pytest.approx(30.0)
    np.testing.assert_allclose(unwrapped.range_m, true, rtol=0, atol=0.02)
    assert np.all(unwrapped.confidence > 1 - 1e-12)


# --- the search equals the exhaustive one ----------------------------------------------------------------------

@settings(max_examples=200, deadline=None, derandomize=True)
@given(row=noisy_rows())
def test_unwrap_depths__equals_the_exhaustive_search_over_every_tuple(row):
    # over the combined ambiguity: the least cost of all wrap-count tuples whose range lies in [0, L)
    freqs, depth, sigma, period = row
    result = unwrap_depths(depth[None, :], sigma[None, :], freqs, C)
    x = wrapped(depth, freqs)
    counts = all_tuples(freqs, period)
    ranges, costs = tuple_fits(x, sigma, counts, freqs)
    feasible = (ranges >= 0) & (ranges < period)
    least = costs[feasible].min()
    scale = (1 / sigma**2).sum() * period**2  # what the running sums lose to rounding is relative to this
    assert result.chi2[0] == pytest.approx(least, rel=1e-9, abs=1e-13 * scale)
    # the result is itself one of those tuples, with its range and cost
    own_range, own_cost = tuple_fits(x, sigma, result.wrap_counts.astype(np.int64), freqs)
    assert -1e-12 * period <= result.range_m[0] < period * (1 + 1e-12)  # [0, L) to within rounding
    assert result.range_m[0] == pytest.approx(own_range[0], abs=1e-12 * period)
    assert result.chi2[0] == pytest.approx(own_cost[0], rel=1e-12, abs=1e-12)
    np.testing.assert_allclose(result.depth_m[0], x + result.wrap_counts[0] * C / (2 * freqs), rtol=0, atol=1e-12)
    # confidence: the posterior of the best among the hypotheses, the distinct pieces of the circle
    assume(midpoint_gap(x, freqs, period) > 1e-9)
    pieces = counts[consistent(x, counts, freqs, period)]
    cycles = np.rint(period * 2 * freqs / C).astype(np.int64)  # a period shifts every count by these
    canonical = np.unique(pieces - (pieces[:, :1] // cycles[0]) * cycles, axis=0)
    assert len(canonical) == cycles.sum()  # one hypothesis per midpoint of the circle
    _, piece_costs = tuple_fits(x, sigma, canonical, freqs)
    expected = posterior(piece_costs) * same_side(result.range_m[0], sigma, period)
    assert result.confidence[0] == pytest.approx(expected, abs=1e-6)


@settings(max_examples=200, deadline=None, derandomize=True)
@given(row=noisy_rows(window=True))
def test_unwrap_depths__in_a_shorter_window_equals_the_exhaustive_search_over_its_pieces(row):
    # below the combined ambiguity the hypotheses are the tuples that are the nearest counts of some range in
    # [0, max_range); their least-squares range may stray past either end by the noise
    freqs, depth, sigma, window = row
    x = wrapped(depth, freqs)
    assume(midpoint_gap(x, freqs, window) > 1e-9)
    result = unwrap_depths(depth[None, :], sigma[None, :], freqs, C, max_range_m=window)
    counts = all_tuples(freqs, window)
    pieces = counts[consistent(x, counts, freqs, window)]
    _, costs = tuple_fits(x, sigma, pieces, freqs)
    scale = (1 / sigma**2).sum() * window**2
    assert result.chi2[0] == pytest.approx(costs.min(), rel=1e-9, abs=1e-13 * scale)
    own = result.wrap_counts[0].astype(np.int64)
    assert any(np.array_equal(own, p) for p in pieces)
    assert result.confidence[0] == pytest.approx(posterior(costs), abs=1e-6)


def test_unwrap_depths__near_zero_a_window_keeps_the_range_and_the_circle_goes_round():
    depth = (RANGES - 1e-5)[None, :]  # every frequency measured 10 um short of its wrap: range -10 um
    sigma = np.full((1, 4), 1e-4)
    window = unwrap_depths(depth, sigma, FREQS, C, max_range_m=20.0)
    assert window.range_m[0] == pytest.approx(-1e-5, abs=1e-12)
    np.testing.assert_array_equal(window.wrap_counts[0], [-1, -1, -1, -1])
    circle = unwrap_depths(depth, sigma, FREQS, C)  # 0 and 24 m are the same range over the combined ambiguity
    assert circle.range_m[0] == pytest.approx(24.0 - 1e-5, abs=1e-12)
    np.testing.assert_array_equal(circle.wrap_counts[0], [1, 2, 3, 4])
    # ... but the counts are right only if the range is too: 10 um from the end, with an sd of 50 um
    assert circle.confidence[0] == pytest.approx(1 - 0.5 * math.erfc(0.2 / math.sqrt(2)), rel=1e-9)
    assert ambiguous(circle)[0] and window.confidence[0] == 1.0


def test_unwrap_depths__frequencies_without_a_common_divisor_unwrap_in_an_explicit_window():
    freqs = np.array([12.5e6, 18.7501234e6])  # no common divisor of 1 kHz
    true = np.linspace(0.1, 19.9, 200)
    sigma = np.tile([2e-3, 1.5e-3], (200, 1))
    depth = noisy(true, sigma, np.random.default_rng(5), freqs)
    with pytest.raises(MpiLidarError, match="give an explicit max_range_m"):
        unwrap_depths(depth, sigma, freqs, C)
    unwrapped = unwrap_depths(depth, sigma, freqs, C, max_range_m=20.0)
    np.testing.assert_allclose(unwrapped.range_m, true, rtol=0, atol=0.01)


# --- confidence ---------------------------------------------------------------------------------------------

def test_unwrap_depths__two_equally_likely_hypotheses_give_confidence_one_half():
    # ranges 15 and 10 m; 7.5 m at 10 MHz and 0 at 15 MHz fit 8.75 m (7.5 and 10) and 21.25 m (22.5 and 20)
    # equally well, each with residuals of 1.25 m; every other tuple misses by 3.75 m or more
    freqs = np.array([10e6, 15e6])
    unwrapped = unwrap_depths(np.array([[7.5, 0.0]]), np.ones((1, 2)), freqs, C)
    assert unwrapped.chi2[0] == pytest.approx(2 * 1.25**2, rel=1e-12)
    assert unwrapped.range_m[0] in (pytest.approx(8.75), pytest.approx(21.25))
    others = np.exp(-0.5 * (2 * 3.75**2 - 2 * 1.25**2))  # the two next-best: residuals of 3.75 m
    assert unwrapped.confidence[0] == pytest.approx(1 / (2 + 2 * others), rel=1e-6)
    assert ambiguous(unwrapped)[0]


def test_unwrap_depths__noise_far_beyond_every_range_leaves_all_14_hypotheses_alike():
    rng = np.random.default_rng(6)
    sigma = np.full(4, 1e3)
    unwrapped = unwrap_depths(rng.uniform(0, 4.8, (100, 4)), np.tile(sigma, (100, 1)), FREQS, C)
    # sum over the circle of L / A_f = 2 + 3 + 4 + 5 pieces, costs within (4.8 m / 1 km)^2 of each other; each
    # range, with an sd of 500 m, lies on its side of the circle's end with probability about 1/2
    expected = [same_side(r, sigma, 24.0) / 14 for r in unwrapped.range_m]
    np.testing.assert_allclose(unwrapped.confidence, expected, rtol=1e-3)
    assert ambiguous(unwrapped).all()


def test_unwrap_depths__midpoints_that_coincide_bound_no_hypothesis_between_them():
    # depths all 0: the 18.75 and 31.25 MHz lattices both change their nearest count at 12 m (4 + 8 and
    # 2.4 + 2 x 4.8), so no range has the one count raised and not the other: 13 hypotheses, not 14
    unwrapped = unwrap_depths(np.zeros((1, 4)), np.full((1, 4), 1e3), FREQS, C)
    assert unwrapped.confidence[0] == pytest.approx(same_side(unwrapped.range_m[0], np.full(4, 1e3), 24.0) / 13,
                                                    rel=1e-3)


def test_unwrap_depths__confidence_predicts_the_share_of_wrong_counts_under_gaussian_noise():
    rng = np.random.default_rng(7)
    n = 40_000
    true = rng.uniform(0, 24, n)
    sigma = np.tile(0.45 * SD_RATIOS, (n, 1))  # the top frequency's sd: 0.45 m, where a few % go wrong
    unwrapped = unwrap_depths(noisy(true, sigma, rng), sigma, FREQS, C)
    wrong = np.abs(unwrapped.range_m - true) > 2.4  # a wrong count, or a range across the end of the circle
    predicted = float((1 - unwrapped.confidence).sum())
    assert 300 < predicted < 3000  # a few % of 40,000: the test has something to measure
    assert abs(wrong.sum() - predicted) < 4 * np.sqrt(predicted)
    kept = ~ambiguous(unwrapped)
    assert wrong[kept].sum() <= max(5, 3 * (1 - unwrapped.confidence[kept]).sum())


# --- rows, chunks, errors -----------------------------------------------------------------------------------

@pytest.mark.parametrize(("column", "bad"), [("depth", np.nan), ("sigma", np.nan), ("depth", np.inf),
                                             ("sigma", np.inf), ("depth", -np.inf)])
def test_unwrap_depths__a_row_with_a_non_finite_value_is_nan_with_confidence_zero(column, bad):
    rng = np.random.default_rng(8)
    true = rng.uniform(0, 24, 5)
    sigma = np.full((5, 4), 0.01)
    depth = noisy(true, sigma, rng)
    alone = unwrap_depths(depth, sigma, FREQS, C)
    (depth if column == "depth" else sigma)[2, 1] = bad
    result = unwrap_depths(depth, sigma, FREQS, C)
    assert np.isnan(result.depth_m[2]).all() and np.isnan(result.range_m[2]) and np.isnan(result.chi2[2])
    assert result.confidence[2] == 0.0 and ambiguous(result)[2]
    np.testing.assert_array_equal(result.wrap_counts[2], 0)
    keep = [0, 1, 3, 4]
    np.testing.assert_array_equal(result.range_m[keep], alone.range_m[keep])
    np.testing.assert_array_equal(result.confidence[keep], alone.confidence[keep])


def test_unwrap_depths__chunked_rows_give_the_same_result(monkeypatch):
    rng = np.random.default_rng(9)
    true = rng.uniform(0, 24, 103)
    sigma = rng.uniform(0.01, 0.4, (103, 1)) * SD_RATIOS
    depth = noisy(true, sigma, rng)
    whole = unwrap_depths(depth, sigma, FREQS, C)
    monkeypatch.setattr(unwrap, "CHUNK_ROWS", 10)
    chunked = unwrap_depths(depth, sigma, FREQS, C)
    for field in ("depth_m", "range_m", "confidence", "wrap_counts", "chi2"):
        np.testing.assert_array_equal(getattr(chunked, field), getattr(whole, field), err_msg=field)


def test_unwrap_depths__no_rows_give_empty_results():
    result = unwrap_depths(np.empty((0, 4)), np.empty((0, 4)), FREQS, C)
    assert result.depth_m.shape == (0, 4) and result.range_m.shape == (0,) and result.wrap_counts.shape == (0, 4)


@pytest.mark.parametrize(("kwargs", "message"), [
    ({"sigma_m": np.zeros((2, 4))}, "sds must be positive"),
    ({"sigma_m": np.ones((2, 3))}, "shape"),
    ({"depth_m": np.ones(4)}, "shape"),
    ({"max_range_m": 24.1}, "exceeds the frequencies' combined ambiguity"),
    ({"max_range_m": 0.0}, "positive distance"),
    ({"max_range_m": float("nan")}, "positive distance"),
    ({"frequencies_hz": (12.5e6, 12.501e6, 25e6, 31.25e6)}, "more than 1024"),  # gcd 1 kHz: 150 km
    ({"frequencies_hz": (12.5e6, -18.75e6, 25e6, 31.25e6), "max_range_m": 10.0}, "positive modulation"),
    ({"c": 0.0}, "speed of light"),
])
def test_unwrap_depths__refuses_inputs_it_cannot_search(kwargs, message):
    arguments = {"depth_m": np.ones((2, 4)), "sigma_m": np.ones((2, 4)), "frequencies_hz": FREQS, "c": C,
                 **kwargs}
    with pytest.raises(MpiLidarError, match=message):
        unwrap_depths(**arguments)


def test_unwrap_depths__max_range_equal_to_the_combined_ambiguity_is_the_default():
    rng = np.random.default_rng(10)
    sigma = np.full((200, 4), 0.2)
    depth = noisy(rng.uniform(0, 24, 200), sigma, rng)
    default = unwrap_depths(depth, sigma, FREQS, C)
    explicit = unwrap_depths(depth, sigma, FREQS, C, max_range_m=24.0 * (1 + 1e-12))
    np.testing.assert_array_equal(explicit.range_m, default.range_m)


def test_ambiguous__is_confidence_below_the_threshold():
    result = Unwrapped(np.zeros((4, 1)), np.zeros(4), np.array([0.0, 0.998, MIN_UNWRAP_CONFIDENCE, 1.0]),
                       np.zeros((4, 1), np.int16), np.zeros(4))
    np.testing.assert_array_equal(ambiguous(result), [True, True, False, False])
    np.testing.assert_array_equal(ambiguous(result, min_confidence=0.5), [True, False, False, False])
    assert MIN_UNWRAP_CONFIDENCE == 0.999


# --- the simulator ------------------------------------------------------------------------------------------

def test_unwrap_depths__simulated_pixels_at_10_m_and_albedo_half_all_unwrap():
    # Table I noise, no multipath: sds about 91, 61, 46 and 37 mm. The nearest wrong hypothesis lies 2.1 sds of
    # the 31.25 MHz depth (sds in these ratios) x sqrt(4.5) / 0.037 m away, 57 sds: no pixel of 100,000 went
    # wrong when this was measured, so none of 20,000 may.
    config = Config()
    theta = np.tile([10.0, 0.0, 0.5, 0.0, 0.0, 0.0], (20_000, 1))
    depth, amplitude = MomentSensor(config).measure(theta, np.random.default_rng(11))
    sigma = depth_noise_m(SensorConfig(), config.frequencies_hz, amplitude)
    assert np.all(depth < RANGES)  # the simulator reports wrapped depths
    np.testing.assert_allclose(np.median(sigma, axis=0), [0.091, 0.061, 0.046, 0.037], rtol=0.05)
    unwrapped = unwrap_depths(depth, sigma, config.frequencies_hz, config.sensor.speed_of_light_m_per_s)
    assert np.all(np.abs(unwrapped.range_m - 10.0) < 0.2)
    np.testing.assert_array_equal(unwrapped.wrap_counts, np.broadcast_to([0, 1, 1, 2], depth.shape))
    assert not ambiguous(unwrapped).any()
    # the inverse-variance weighted range has the sd of the weights: 25 mm
    expected_sd = np.median(1 / np.sqrt((1 / sigma**2).sum(axis=1)))
    assert unwrapped.range_m.std() == pytest.approx(expected_sd, rel=0.05)
    # chi2 with 3 degrees of freedom
    assert np.mean(unwrapped.chi2) == pytest.approx(3.0, rel=0.05)
