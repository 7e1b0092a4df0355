"""Numerical stress suite: wraps, precision, extreme signals, parameter corners, degenerate fits, extrapolation.

Each test drives the physics or the correction path to an edge and checks that every output is finite or
flagged invalid (never a silent NaN or a jump of a whole unambiguous range).
"""

from __future__ import annotations

import itertools

import numpy as np
import pytest
import xgboost as xgb
from hypothesis import given, settings
from hypothesis import strategies as st

from mpi_lidar.config import PAPER_FREQUENCIES_HZ, Config, PriorConfig, SensorConfig
from mpi_lidar.correction import INVALID_FLAGS, CorrectionOptions, Flag, correct_scan, validity_flags
from mpi_lidar.learning.features import FeatureSpec
from mpi_lidar.learning.limits import posterior_estimates
from mpi_lidar.learning.model import CorrectionModel
from mpi_lidar.learning.model_card import DatasetCard
from mpi_lidar.learning.train import TrainResult, model_card
from mpi_lidar.physics import demod, make_sensor
from mpi_lidar.physics.inverse import (
    FIT_OK,
    NOT_FINITE,
    OUT_OF_BOUNDS,
    SINGLE_PATH,
    least_squares_two_path,
    prony_two_path,
)
from mpi_lidar.physics.moments import MomentSensor
from mpi_lidar.physics.noise import NoiseModel
from mpi_lidar.physics.transport import two_path_phase_bias
from mpi_lidar.scans.scan import Scan
from mpi_lidar.simulation.sampling import sample_theta

pytestmark = pytest.mark.unit

FREQS = np.array(PAPER_FREQUENCIES_HZ)
C = 3.0e8
RANGES = C / (2 * FREQS)  # 12, 8, 6, 4.8 m
STATUSES = {int(FIT_OK), int(SINGLE_PATH), int(OUT_OF_BOUNDS), int(NOT_FINITE)}


def _circular_error(depth: np.ndarray, truth: np.ndarray) -> np.ndarray:
    """Depth error modulo each frequency's unambiguous range, in (-R/2, R/2]. [m]"""
    return (depth - truth + RANGES / 2) % RANGES - RANGES / 2


def _single_path(d_as, rho=1.0) -> np.ndarray:
    d_as = np.atleast_1d(np.asarray(d_as, dtype=np.float64))
    rho = np.broadcast_to(np.asarray(rho, dtype=np.float64), d_as.shape)
    return np.column_stack([d_as, np.zeros_like(d_as), rho, rho, np.zeros_like(d_as), rho])


# --- phase wrap at every frequency ------------------------------------------------------------------------

WRAPS = [(j, k) for j in range(4) for k in range(1, int(12 // RANGES[j]) + 1)]


@settings(max_examples=40, deadline=None, derandomize=True)
@given(wrap=st.sampled_from(WRAPS),
       offset=st.one_of(st.just(0.0), st.floats(-1e-3, 1e-3), st.sampled_from([-1e-12, 1e-12, -1e-9, 1e-9])))
def test_measure__noiseless_depth_around_every_wrap_point(wrap, offset):
    j, k = wrap
    d_as = k * RANGES[j] + offset
    config = Config().replace(simulator={"noise_scale": 0.0, "round_photons": False, "whole_cycles": True})
    depth, amplitude = MomentSensor(config).measure(_single_path(d_as), np.random.default_rng(0))
    assert np.all((depth >= 0) & (depth < RANGES)) and np.all(np.isfinite(amplitude))
    np.testing.assert_allclose(_circular_error(depth[0], d_as), 0.0, atol=1e-7)


@pytest.mark.parametrize("d_as", [2.4, 4.8, 6.0, 8.0, 12.0 - 1e-6])
def test_measure__noisy_depth_at_wrap_points_stays_in_range_with_predicted_noise(d_as):
    sensor = MomentSensor(Config())
    theta = _single_path(np.full(2000, d_as), 1.0)
    depth, amplitude = sensor.measure(theta, np.random.default_rng(1))
    assert np.all((depth >= 0) & (depth < RANGES)) and np.all(np.isfinite(amplitude))
    _, cov = sensor.quadrature_moments(theta[:1])
    sigma_m = np.sqrt(0.5 * np.trace(cov[0], axis1=-2, axis2=-1)) / amplitude.mean(0) * C / (4 * np.pi * FREQS)
    # modulo the range the error is noise (6 sigma); a wrong wrap convention would put readings R/2 away
    assert np.all(np.abs(_circular_error(depth, d_as)) < 6 * sigma_m)
    if d_as == 4.8:  # exactly on the 31.25 MHz wrap: readings straddle it, at both ends of [0, R)
        assert (depth[:, 3] < 0.05).any() and (depth[:, 3] > RANGES[3] - 0.05).any()


def test_prony_two_path__recovers_depth_across_the_31p25_mhz_wrap():
    d_as = np.array([4.8 - 1e-4, 4.8, 4.8 + 1e-4])
    theta = _single_path(d_as, 0.8)
    theta[:, 1], theta[:, 4] = 0.1, 0.5
    config = Config().replace(simulator={"noise_scale": 0.0, "round_photons": False, "whole_cycles": True})
    depth, amplitude = MomentSensor(config).measure(theta, np.random.default_rng(0))
    fit = prony_two_path(np.hstack([depth, amplitude]), FREQS)
    assert np.all(fit.status == FIT_OK)
    np.testing.assert_allclose(fit.direct_depth_m, d_as, rtol=0, atol=1e-6)


# --- float32 against float64 through demodulation, large DC --------------------------------------------------


@settings(max_examples=40, deadline=None, derandomize=True)
@given(phase=st.floats(0, 2 * np.pi, exclude_max=True), dc_over_swing=st.floats(0, 1e4),
       frequency_index=st.integers(0, 3))
def test_correlate_taps__float32_voltage_with_large_dc_is_summed_in_float64(phase, dc_over_swing, frequency_index):
    f = FREQS[frequency_index]
    bins = demod.integration_bins(16e-6, 6e-9, f, whole_cycles=True)
    wt = 2 * np.pi * f * demod.bin_times(bins, 6e-9)
    swing = 1e-3
    voltage64 = dc_over_swing * swing + swing * np.cos(wt - phase)
    voltage32 = voltage64.astype(np.float32)
    taps32 = demod.correlate_taps(voltage32, f, 6e-9, 0.4785)
    assert taps32.dtype == np.float64
    np.testing.assert_array_equal(taps32, demod.correlate_taps(voltage32.astype(np.float64), f, 6e-9, 0.4785))
    phi64 = demod.phase_from_taps(demod.correlate_taps(voltage64, f, 6e-9, 0.4785))
    phi32 = demod.phase_from_taps(taps32)
    # float32 storage rounds each bin by <= 2^-24 |V|: each tap moves by <= m 2^-24 max|V|, against a tap
    # amplitude of m * swing / 2 (worst case, all bins' errors aligned).
    bound = 2.0**-22 * (dc_over_swing + 1) + 1e-12
    assert abs((phi32 - phi64 + np.pi) % (2 * np.pi) - np.pi) <= bound
    assert abs((phi64 - phase + np.pi) % (2 * np.pi) - np.pi) < 1e-9


@settings(max_examples=40, deadline=None, derandomize=True)
@given(phase=st.floats(0, 2 * np.pi, exclude_max=True), dc_over_amplitude=st.floats(0, 1e5))
def test_phase_from_taps__float32_taps_with_dc_lose_at_most_their_storage_precision(phase, dc_over_amplitude):
    amplitude = 1e-3
    taps64 = dc_over_amplitude * amplitude + amplitude * np.cos(phase + demod.TAP_SHIFTS_RAD)
    taps32 = taps64.astype(np.float32)
    # differences are formed in float64: the only loss is the float32 storage of each tap
    np.testing.assert_array_equal(demod.phase_from_taps(taps32), demod.phase_from_taps(taps32.astype(np.float64)))
    error = abs((demod.phase_from_taps(taps32) - phase + np.pi) % (2 * np.pi) - np.pi)
    assert error <= 2.0**-22 * (dc_over_amplitude + 1) + 1e-12
    assert abs((demod.phase_from_taps(taps64) - phase + np.pi) % (2 * np.pi) - np.pi) <= 1e-15 * (
        dc_over_amplitude + 1) * 8 + 1e-15
    # the documented float32 pitfall: a DC 1e4 times the swing costs float32 taps up to ~1 mm at 31.25 MHz
    if dc_over_amplitude > 1e4:
        assert 2.0**-22 * dc_over_amplitude * C / (4 * np.pi * FREQS[3]) > 1e-3


# --- amplitudes from zero to saturation -----------------------------------------------------------------------


def test_measure__zero_to_saturated_returns_are_finite_and_flagged():
    rho = np.array([0.0, 1e-9, 1e-6, 1e-3, 0.14, 1.0])
    d_as = np.array([0.1, 0.2, 0.5, 1.4, 2.4])
    grid = np.array(list(itertools.product(d_as, rho)))
    theta = _single_path(grid[:, 0], grid[:, 1])
    options = CorrectionOptions(gate="all", saturation_amplitude_v2=0.7176)  # a threshold given, as a profile does
    for fidelity in ("moment", "waveform"):
        config = Config().replace(simulator={"fidelity": fidelity})
        depth, amplitude = make_sensor(config).measure(theta, np.random.default_rng(2))
        raw = np.hstack([depth, amplitude])
        assert np.all(np.isfinite(raw)) and np.all(amplitude >= 0)
        assert np.all((depth >= 0) & (depth < RANGES))
        flags = validity_flags(raw, options, NoiseModel.for_sensor(SensorConfig(), PAPER_FREQUENCIES_HZ))
        no_light = grid[:, 1] == 0
        assert np.all(np.isin(flags[no_light], [Flag.NO_RETURN, Flag.INCONSISTENT]))
        saturated = (0.1794 * grid[:, 1] / grid[:, 0] ** 2) > 1.2 * options.saturation_amplitude_v2
        assert saturated.sum() >= 2 and np.all(flags[saturated] == Flag.SATURATED)
        # a clean, well-lit return is valid
        clean = (grid[:, 1] >= 0.14) & (0.1794 * grid[:, 1] / grid[:, 0] ** 2 < 0.8 * options.saturation_amplitude_v2)
        assert np.all(flags[clean] == Flag.NOT_NEEDED)


# --- parameter corners --------------------------------------------------------------------------------------

CORNERS = np.array([[d, e, *rhos] for d in (1.4, 2.4) for e in (0.0, 0.15)
                    for rhos in itertools.product((0.0, 1.0), repeat=4)])


def test_corners__simulators_solvers_and_posterior_stay_finite():
    for fidelity in ("moment", "waveform"):
        config = Config().replace(simulator={"fidelity": fidelity})
        depth, amplitude = make_sensor(config).measure(CORNERS, np.random.default_rng(3))
        raw = np.hstack([depth, amplitude])
        assert np.all(np.isfinite(raw)) and np.all((depth >= 0) & (depth < RANGES))
        for solver in (prony_two_path, least_squares_two_path):
            fit = solver(raw, FREQS)
            assert set(np.unique(fit.status).tolist()) <= STATUSES
            for field in ("direct_depth_m", "path_offset_m", "direct_amplitude", "multipath_amplitude"):
                assert np.all(np.isfinite(getattr(fit, field))), (solver.__name__, field)
    lit = CORNERS[:, 2] == 1.0  # the posterior needs a return; rho_SAS = 0 rows are flagged NO_RETURN upstream
    est = posterior_estimates(raw[lit], Config(), np.random.default_rng(4), pool=100, stages=2)
    assert np.all(np.isfinite(est.median_m)) and np.all(np.isfinite(est.mean_m)) and np.all(np.isfinite(est.std_m))
    # ess 0 flags rows the prior cannot produce (e.g. rho_ABA = 1 with d_AB = 0.15 m); the others are sampled
    assert np.all((est.ess == 0) | (est.ess >= 1)) and (est.ess >= 1).mean() > 0.5


@settings(max_examples=25, deadline=None, derandomize=True)
@given(corner=st.integers(0, len(CORNERS) - 1), noise_scale=st.sampled_from([0.0, 1e-3, 1.0, 10.0]),
       round_photons=st.booleans(), whole_cycles=st.booleans(),
       d_as=st.sampled_from([0.05, 1.4, 2.4, 30.0]))
def test_quadrature_moments__covariance_psd_at_corners_and_extreme_signals(corner, noise_scale, round_photons,
                                                                            whole_cycles, d_as):
    theta = CORNERS[corner : corner + 1].copy()
    theta[0, 0] = d_as  # 0.05 m: ~7e6 photons per bin at the peak; 30 m: a few hundred
    sim = {"noise_scale": noise_scale, "round_photons": round_photons, "whole_cycles": whole_cycles}
    mean, cov = MomentSensor(Config().replace(simulator=sim)).quadrature_moments(theta)
    assert np.all(np.isfinite(mean)) and np.all(np.isfinite(cov))
    np.testing.assert_array_equal(cov, np.swapaxes(cov, -1, -2))
    eig = np.linalg.eigvalsh(cov)
    trace = np.trace(cov, axis1=-2, axis2=-1)
    assert np.all(eig >= -1e-12 * trace[..., None])
    if noise_scale > 0:  # thermal and TIA noise keep it positive definite even without light
        assert np.all(eig > 0)


# --- Prony near degenerate poles ------------------------------------------------------------------------------


@settings(max_examples=60, deadline=None, derandomize=True)
@given(d_as=st.floats(0.5, 10.0), d_ab=st.one_of(st.just(0.0), st.floats(1e-12, 0.02)), ratio=st.floats(0.0, 1.0),
       noise=st.sampled_from([0.0, 1e-9, 1e-6]), seed=st.integers(0, 2**16))
def test_prony_two_path__near_degenerate_poles_error_bounded_by_single_path_bias(d_as, d_ab, ratio, noise, seed):
    w = 4 * np.pi * FREQS / C
    z = np.exp(1j * w * d_as) * (1 + ratio * np.exp(1j * w * d_ab))
    rng = np.random.default_rng(seed)
    z = z + noise * np.abs(z).mean() * (rng.standard_normal(4) + 1j * rng.standard_normal(4))
    raw = np.concatenate([np.mod(np.angle(z), 2 * np.pi) / w, np.abs(z)])[None, :]
    fit = prony_two_path(raw, FREQS)
    assert int(fit.status[0]) in STATUSES - {int(NOT_FINITE)}
    assert np.isfinite(fit.direct_depth_m[0]) and np.isfinite(fit.path_offset_m[0])
    bias = np.abs(two_path_phase_bias(ratio, w * d_ab) / w).max()
    noise_depth = 10 * noise / w.min()
    if fit.status[0] == FIT_OK:
        # a two-path fit this close to degenerate may not beat the single path, but stays within its error
        # plus what the fit's conditioning (~1e-16 / (ratio * (w d_AB)^2)) allows
        allowed = bias + noise_depth / max(ratio * (0.26 * d_ab) ** 2, 1e-30) * 1e-3 + 1e-6
        assert abs(fit.direct_depth_m[0] - d_as) <= max(allowed, 0.02)
    else:
        assert abs(fit.direct_depth_m[0] - d_as) <= bias + noise_depth + 1e-9


# --- a trained model outside its training range ---------------------------------------------------------------


@pytest.fixture(scope="module")
def tiny_model() -> CorrectionModel:
    config = Config(prior=PriorConfig())  # the paper's prior: 1.4-2.4 m, the range the cases below test
    rng = np.random.default_rng(5)
    theta = sample_theta(config.prior, 3000, rng)
    depth, amplitude = make_sensor(config).measure(theta, rng)
    raw = np.hstack([depth, amplitude])
    spec = FeatureSpec(PAPER_FREQUENCIES_HZ, "engineered", "residual")
    booster = xgb.train({"max_depth": 3, "eta": 0.3, "nthread": 1}, xgb.DMatrix(spec.transform(raw),
                        label=spec.target(raw, theta[:, 0])), num_boost_round=20)
    result = TrainResult(booster, 19, float("nan"), 3000, 0, 0.0)
    return CorrectionModel(booster, model_card(spec, DatasetCard.from_config(config), None, result, workers=0))


def test_predict_depth__finite_outside_training_range(tiny_model):
    config = Config().replace(prior={"d_as_m": (2.4, 3.0)})
    rng = np.random.default_rng(6)
    theta = sample_theta(config.prior, 500, rng)
    depth, amplitude = make_sensor(config).measure(theta, rng)
    raw = np.hstack([depth, amplitude])
    extremes = np.array([
        [0.0] * 4 + [1e-12] * 4,  # no return
        [11.9, 7.9, 5.9, 4.7] + [50.0] * 4,  # far and saturated
        [2.0, 2.0, 2.0, 2.0, 1e-30, 1.0, 1e-30, 1.0],  # wildly inconsistent amplitudes
        [0.0, 8.0, 0.0, 4.8] + [0.1] * 4,  # depths at the range ends
    ])
    prediction = tiny_model.predict_depth(np.vstack([raw, extremes]).astype(np.float32))
    assert np.all(np.isfinite(prediction))
    # extrapolating trees return a bounded correction: never more than the largest residual they learnt
    assert np.abs(prediction[:500] - raw[:, 3]).max() < 0.1


def test_correct_scan__every_pixel_finite_or_flagged_invalid(tiny_model):
    # 20 pixels, too few to read their amplitude unit: given, V^2
    config = Config()
    rng = np.random.default_rng(7)
    d_as = np.concatenate([np.linspace(1.4, 2.3, 8), np.linspace(2.5, 3.0, 8), [0.2, 0.2, 2.0, 2.0]])
    theta = _single_path(d_as, 0.7)
    theta[:16, 1], theta[:16, 4] = 0.08, 0.6
    theta[16:18, 2:] = 1.0  # saturated
    theta[18, [2, 3, 5]] = 0.0  # no return
    depth, amplitude = make_sensor(config).measure(theta, rng)
    depth[19, 1] = np.nan  # a corrupted pixel
    h, w = 4, 5
    scan = Scan(name="stress", frequencies_hz=PAPER_FREQUENCIES_HZ,
                depth=depth.T.reshape(4, h, w).astype(np.float32),
                amplitude=amplitude.T.reshape(4, h, w).astype(np.float32))
    result = correct_scan(scan, tiny_model, CorrectionOptions(gate="all", amplitude_scale=1.0, baseline="raw",
                                                              saturation_amplitude_v2=0.7176))
    flags = result.flags.ravel()
    out = result.depth.ravel()
    invalid = np.isin(flags, [int(f) for f in INVALID_FLAGS])
    assert np.all(np.isfinite(out[~invalid])) and np.all(np.isnan(out[invalid]))
    assert flags[19] == Flag.NOT_FINITE and flags[18] == Flag.NO_RETURN
    assert np.all(flags[16:18] == Flag.SATURATED)
    # beyond the training prior: left as measured; where a made-up grid puts strong multipath beside a 10 cm step,
    # flagged as a depth edge's mixed pixel
    assert np.all(np.isin(flags[8:16], [Flag.OUT_OF_RANGE, Flag.MIXED])) and (flags[8:16] == Flag.OUT_OF_RANGE).any()
    kept = flags[8:16] == Flag.OUT_OF_RANGE
    np.testing.assert_array_equal(out[8:16][kept], depth[8:16, 3][kept].astype(np.float32))
    assert np.all(np.isin(flags[:8], [Flag.CORRECTED, Flag.MIXED])) and (flags[:8] == Flag.CORRECTED).sum() >= 4


def test_correct_scan__nearer_than_the_prior_is_corrected_down_to_the_near_fraction(tiny_model):
    # multipath only lengthens a path: a depth measured below the prior's 1.4 m is truly that near, and the
    # default rule trusts the model down to 15 % nearer (1.19 m); nearer still, and past 2.4 m, raw depth stays
    config = Config()
    d_as = np.repeat([1.25, 1.30, 1.05, 1.10], 5)
    theta = _single_path(d_as, 0.7)
    theta[:, 1], theta[:, 4] = 0.05, 0.3  # multipath, so the measured depths lie above the true ones
    depth, amplitude = make_sensor(config).measure(theta, np.random.default_rng(8))
    scan = Scan(name="near", frequencies_hz=PAPER_FREQUENCIES_HZ, depth=depth.T.reshape(4, 4, 5).astype(np.float32),
                amplitude=amplitude.T.reshape(4, 4, 5).astype(np.float32))
    flags = correct_scan(scan, tiny_model, CorrectionOptions(gate="all", amplitude_scale=1.0)).flags.ravel()
    assert np.all(flags[:10] == Flag.CORRECTED) and np.all(flags[10:] == Flag.OUT_OF_RANGE)
    strict_options = CorrectionOptions(gate="all", near_range_fraction=0.0, amplitude_scale=1.0)
    strict = correct_scan(scan, tiny_model, strict_options).flags
    assert np.all(strict == Flag.OUT_OF_RANGE)
