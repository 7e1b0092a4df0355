"""Parallel-phase 4-tap demodulation, paper eq 2-7."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from mpi_lidar.physics import demod

pytestmark = pytest.mark.unit

C = 3.0e8
BIN_S = 6e-9
FREQS = (12.5e6, 18.75e6, 25e6, 31.25e6)
TWO_PI = 2 * np.pi


@pytest.mark.parametrize("frequency_hz", FREQS)
def test_integration_bins__default_window_is_2667_bins(frequency_hz):
    # K = round(16 us / 6 ns), the same for every frequency, and not a whole number of cycles
    k = demod.integration_bins(16e-6, BIN_S, frequency_hz, whole_cycles=False)
    assert k == 2667
    cycles = k * frequency_hz * BIN_S
    assert abs(cycles - round(cycles)) > 1e-3


@pytest.mark.parametrize(("frequency_hz", "period", "expected"),
                         [(12.5e6, 40, 2680), (18.75e6, 80, 2640), (25e6, 20, 2660), (31.25e6, 16, 2672)])
def test_integration_bins__whole_cycles_snaps_to_nearest_multiple(frequency_hz, period, expected):
    assert demod.whole_cycle_bins(frequency_hz, BIN_S) == period
    k = demod.integration_bins(16e-6, BIN_S, frequency_hz, whole_cycles=True)
    assert k == expected
    assert k % period == 0 and abs(k - 2667) <= period / 2
    cycles = k * frequency_hz * BIN_S
    assert abs(cycles - round(cycles)) < 1e-9


def test_whole_cycle_bins__raises_when_no_window_exists():
    with pytest.raises(ValueError, match="no whole-cycle window"):
        demod.whole_cycle_bins(12.5e6 + 1, BIN_S, max_bins=10_000)


def test_bin_times__start_of_each_bin():
    np.testing.assert_allclose(demod.bin_times(4, BIN_S), [0, 6e-9, 12e-9, 18e-9], rtol=1e-15)


@settings(max_examples=40, deadline=None, derandomize=True)
@given(phase=st.floats(0, TWO_PI), dc=st.floats(0, 2.0), swing=st.floats(1e-4, 2.0))
def test_correlate_taps__whole_cycles_closed_form(phase, dc, swing):
    # V_i = A + B cos(w t_i - phi) over whole cycles gives C_n = (m B / 2) cos(phi + n pi / 2)
    f, m = 31.25e6, 0.4785
    k = demod.integration_bins(16e-6, BIN_S, f, whole_cycles=True)
    wt = TWO_PI * f * demod.bin_times(k, BIN_S)
    taps = demod.correlate_taps(dc + swing * np.cos(wt - phase), f, BIN_S, m)
    expected = m * swing / 2 * np.cos(phase + demod.TAP_SHIFTS_RAD)
    np.testing.assert_allclose(taps, expected, rtol=0, atol=1e-12 * (dc + swing))
    circular_error = np.angle(np.exp(1j * (demod.phase_from_taps(taps) - phase)))
    assert abs(circular_error) < 1e-9
    assert demod.amplitude_from_taps(taps) == pytest.approx(m * swing / 2, rel=1e-9)


def test_correlate_taps__batched_rows_equal_single_rows(rng):
    voltage = rng.normal(1.0, 0.1, size=(3, 2, 500))
    batched = demod.correlate_taps(voltage, 25e6, BIN_S, 0.4785)
    assert batched.shape == (3, 2, 4)
    for i in range(3):
        for j in range(2):
            np.testing.assert_allclose(batched[i, j], demod.correlate_taps(voltage[i, j], 25e6, BIN_S, 0.4785),
                                       rtol=1e-13)


def test_taps_from_quadratures__parallel_phase_structure():
    taps = demod.taps_from_quadratures([1.0, -2.0], [3.0, 0.5])
    np.testing.assert_array_equal(taps, [[1.0, -3.0, -1.0, 3.0], [-2.0, -0.5, 2.0, 0.5]])
    np.testing.assert_allclose(demod.amplitude_from_taps(taps), np.hypot([1.0, -2.0], [3.0, 0.5]), rtol=1e-15)
    np.testing.assert_allclose(demod.phase_from_taps(taps), np.mod(np.arctan2([3.0, 0.5], [1.0, -2.0]), TWO_PI),
                               rtol=1e-15)


def _taps(amplitude, phase, offset=0.0):
    """Ideal taps of a correlation of amplitude Gamma and phase phi, plus an offset common to all four."""
    return offset + amplitude * np.cos(np.asarray(phase)[..., None] + demod.TAP_SHIFTS_RAD)


@settings(max_examples=50, deadline=None, derandomize=True)
@given(phase=st.floats(0, TWO_PI, exclude_max=True), amplitude=st.floats(1e-6, 1e3),
       offset=st.floats(-10.0, 10.0))
def test_phase_from_taps__recovers_phase_within_zero_two_pi(phase, amplitude, offset):
    taps = _taps(amplitude, phase, offset)
    got = demod.phase_from_taps(taps)
    assert 0.0 <= got < TWO_PI
    circular_error = np.angle(np.exp(1j * (got - phase)))
    assert abs(circular_error) < 1e-9 * (1 + abs(offset) / amplitude)
    assert demod.amplitude_from_taps(taps) == pytest.approx(amplitude, rel=1e-9, abs=1e-11 * (1 + abs(offset)))


@pytest.mark.parametrize("quadrature", [-1e-20, -1e-300, -5e-324, -1e-17])
def test_phase_from_taps__strictly_below_two_pi(quadrature):
    # C3 - C1 = -tiny, C0 - C2 = 2: atan2 gives -tiny, whose mod 2 pi rounds up to exactly 2 pi unless handled
    taps = np.array([1.0, -quadrature, -1.0, 0.0])
    phase = demod.phase_from_taps(taps)
    assert 0.0 <= phase < TWO_PI
    assert min(phase, TWO_PI - phase) < 1e-15  # and it is the phase 0


def test_phase_from_taps__half_cycle_is_pi_for_either_sign_of_zero():
    # a (-pi, pi] convention would give -pi for a quadrature of -0.0 and throw the depth 4.8 m away
    for quadrature in (0.0, -0.0, 1e-18, -1e-18):
        taps = np.array([-1.0, -quadrature, 1.0, quadrature])
        assert demod.phase_from_taps(taps) == pytest.approx(np.pi, abs=1e-15)


def test_depth_from_phase__eq7_reference_values():
    assert demod.depth_from_phase(np.pi, 31.25e6, C) == pytest.approx(2.4, rel=1e-15)
    np.testing.assert_allclose(demod.depth_from_phase(TWO_PI, np.array(FREQS), C), [12.0, 8.0, 6.0, 4.8],
                               rtol=1e-15)


def test_unambiguous_range__c_over_2f():
    np.testing.assert_allclose(demod.unambiguous_range(np.array(FREQS), C), [12.0, 8.0, 6.0, 4.8], rtol=1e-15)


def test_depth_and_amplitude__per_frequency_columns():
    phase = np.array([[0.5, 1.0, 2.0, np.pi]])
    taps = _taps(np.array([[0.1, 0.2, 0.3, 0.4]])[..., None], phase)
    depth, amplitude = demod.depth_and_amplitude(taps, FREQS, C)
    assert depth.shape == amplitude.shape == (1, 4)
    np.testing.assert_allclose(depth, C * phase / (4 * np.pi * np.array(FREQS)), rtol=1e-12)
    np.testing.assert_allclose(amplitude, [[0.1, 0.2, 0.3, 0.4]], rtol=1e-12)
