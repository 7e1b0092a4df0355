"""Scene-parameter priors, chunk seeding, and the prior's raw-error statistics."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy import stats

from mpi_lidar.config import Config, PriorConfig
from mpi_lidar.physics.demod import depth_and_amplitude
from mpi_lidar.physics.moments import MomentSensor
from mpi_lidar.simulation import dataset
from mpi_lidar.simulation.sampling import SCHEMES, THETA_NAMES, sample_theta
from mpi_lidar.workflows.generate import generate

pytestmark = pytest.mark.unit

N = 20_000
KS_ALPHA = 1e-3


def column(theta: np.ndarray, name: str) -> np.ndarray:
    return theta[:, THETA_NAMES.index(name)]


def assert_uniform(x: np.ndarray, low: float, high: float) -> None:
    assert x.min() >= low and x.max() <= high
    assert stats.kstest(x, stats.uniform(low, high - low).cdf).pvalue > KS_ALPHA


def test_theta_names__order_of_the_columns():
    assert THETA_NAMES == ("d_as_m", "d_ab_m", "rho_sas", "rho_sab", "rho_aba", "rho_bas")
    assert set(SCHEMES) == {"reciprocal", "independent", "explicit"}


@pytest.mark.parametrize("scheme", sorted(SCHEMES))
def test_sample_theta__shape_distances_and_seed(scheme):
    prior = PriorConfig(scheme=scheme)
    theta = sample_theta(prior, N, np.random.default_rng(1))
    assert theta.shape == (N, 6) and theta.dtype == np.float64
    assert_uniform(column(theta, "d_as_m"), 1.4, 2.4)
    assert_uniform(column(theta, "d_ab_m"), 0.0, 0.15)
    assert np.all((theta[:, 2:] >= 0) & (theta[:, 2:] <= 1))
    np.testing.assert_array_equal(theta, sample_theta(prior, N, np.random.default_rng(1)))
    assert not np.array_equal(theta, sample_theta(prior, N, np.random.default_rng(2)))


def test_sample_theta__reciprocal_ties_three_brdfs_to_one_albedo():
    theta = sample_theta(PriorConfig(), N, np.random.default_rng(3))
    rho_sas = column(theta, "rho_sas")
    np.testing.assert_array_equal(column(theta, "rho_sab"), rho_sas)
    np.testing.assert_array_equal(column(theta, "rho_bas"), rho_sas)
    assert_uniform(rho_sas, 0.14, 1.0)
    rho_aba = column(theta, "rho_aba")  # kappa * b with kappa ~ U(0, 1), b ~ U(0.14, 1)
    assert rho_aba.min() >= 0 and rho_aba.max() <= 1.0
    expected_mean = 0.5 * 0.57
    assert abs(rho_aba.mean() - expected_mean) < 5 * rho_aba.std() / np.sqrt(N)
    # E[(kappa b)^2] = E[kappa^2] E[b^2] = (1/3) * (1 - 0.14^3) / (3 * 0.86)
    second_moment = (1 / 3) * (1 - 0.14**3) / (3 * 0.86)
    assert abs(np.mean(rho_aba**2) - second_moment) < 5 * np.std(rho_aba**2) / np.sqrt(N)
    # the coupling at B is drawn apart from the albedo at A
    assert abs(np.corrcoef(rho_sas, rho_aba)[0, 1]) < 4 / np.sqrt(N)


def test_sample_theta__reciprocal_honours_its_ranges():
    prior = PriorConfig(albedo=(0.5, 0.6), coupling=(0.2, 0.3), d_as_m=(3.0, 3.5), d_ab_m=(0.2, 0.25))
    theta = sample_theta(prior, 5_000, np.random.default_rng(4))
    assert_uniform(column(theta, "rho_sas"), 0.5, 0.6)
    assert_uniform(column(theta, "d_as_m"), 3.0, 3.5)
    assert_uniform(column(theta, "d_ab_m"), 0.2, 0.25)
    rho_aba = column(theta, "rho_aba")
    assert rho_aba.min() >= 0.2 * 0.5 and rho_aba.max() <= 0.3 * 0.6


@pytest.mark.parametrize("scheme", sorted(SCHEMES))
def test_sample_theta__no_multipath_fraction_zeroes_that_share_of_rows(scheme):
    fraction = 0.3
    theta = sample_theta(PriorConfig(scheme=scheme, no_multipath_fraction=fraction), N, np.random.default_rng(7))
    zero = column(theta, "rho_aba") == 0.0
    assert abs(zero.mean() - fraction) < 4 * np.sqrt(fraction * (1 - fraction) / N)  # binomial, 4 sigma
    plain = sample_theta(PriorConfig(scheme=scheme), N, np.random.default_rng(7))
    np.testing.assert_array_equal(theta[~zero], plain[~zero])  # the other rows are the scheme's own draws
    np.testing.assert_array_equal(np.delete(theta, THETA_NAMES.index("rho_aba"), axis=1),
                                  np.delete(plain, THETA_NAMES.index("rho_aba"), axis=1))
    assert (column(plain, "rho_aba") > 0).mean() > 0.99


def test_sample_theta__no_multipath_rows_have_no_multipath_bias():
    # the paper's prior: nothing there wraps, so the noiseless depth is the range itself
    config = Config(prior=PriorConfig(no_multipath_fraction=1.0)).replace(simulator={"noise_scale": 0.0})
    theta = sample_theta(config.prior, 200, np.random.default_rng(3))
    taps = MomentSensor(config).taps(theta, np.random.default_rng(4))
    depth, _ = depth_and_amplitude(taps, config.frequencies_hz, config.sensor.speed_of_light_m_per_s)
    np.testing.assert_allclose(depth, np.broadcast_to(theta[:, :1], depth.shape), atol=1e-3)


def test_sample_theta__independent_columns_are_uniform_and_uncorrelated():
    theta = sample_theta(PriorConfig(scheme="independent"), N, np.random.default_rng(5))
    for name in ("rho_sas", "rho_sab", "rho_aba", "rho_bas"):
        assert_uniform(column(theta, name), 0.0, 1.0)
    correlation = np.corrcoef(theta.T)
    off_diagonal = correlation[~np.eye(6, dtype=bool)]
    assert np.abs(off_diagonal).max() < 4.5 / np.sqrt(N)


def test_sample_theta__independent_honours_rho_range():
    theta = sample_theta(PriorConfig(scheme="independent", rho=(0.3, 0.4)), 5_000, np.random.default_rng(6))
    for name in ("rho_sas", "rho_sab", "rho_aba", "rho_bas"):
        assert_uniform(column(theta, name), 0.3, 0.4)


def test_sample_theta__explicit_ranges_honoured():
    ranges = {"rho_sas": (0.2, 0.3), "rho_sab": (0.5, 0.6), "rho_aba": (0.0, 0.1), "rho_bas": (0.9, 1.0)}
    theta = sample_theta(PriorConfig(scheme="explicit", **ranges), 5_000, np.random.default_rng(7))
    for name, (low, high) in ranges.items():
        assert_uniform(column(theta, name), low, high)


interval = st.tuples(st.floats(0, 1), st.floats(0, 1)).map(sorted).map(tuple)


@settings(max_examples=40, deadline=None, derandomize=True)
@given(rho_sas=interval, rho_sab=interval, rho_aba=interval, rho_bas=interval, seed=st.integers(0, 2**32 - 1))
def test_sample_theta__explicit_stays_in_any_ranges(rho_sas, rho_sab, rho_aba, rho_bas, seed):
    prior = PriorConfig(scheme="explicit", rho_sas=rho_sas, rho_sab=rho_sab, rho_aba=rho_aba, rho_bas=rho_bas)
    theta = sample_theta(prior, 200, np.random.default_rng(seed))
    for name, (low, high) in zip(("rho_sas", "rho_sab", "rho_aba", "rho_bas"),
                                 (rho_sas, rho_sab, rho_aba, rho_bas), strict=True):
        x = column(theta, name)
        assert np.all((x >= low) & (x <= high))


# --- chunk seeding ------------------------------------------------------------------------------------------


def small_config(samples: int = 2_000, **simulator: object) -> Config:
    return Config().replace(dataset={"samples": samples, "chunk_rows": 200, "seed": 11}, simulator=simulator)


def chunk_bytes(chunk: dataset.Chunk) -> tuple[bytes, ...]:
    return tuple(getattr(chunk, name).tobytes() for name in ("features", "target", "theta", "split"))


@pytest.mark.parametrize("fidelity", ["moment", "waveform"])
def test_simulate_chunk__bitwise_reproducible(fidelity):
    config = small_config(fidelity=fidelity)
    first = dataset.simulate_chunk(config, 2)
    assert first.features.dtype == np.float32 and first.features.shape == (200, 8)
    assert first.split.dtype == np.uint8 and first.split.sum() == 40  # 20 % test
    dataset.cached_sensor.cache_clear()
    assert chunk_bytes(dataset.simulate_chunk(config, 2)) == chunk_bytes(first)


def test_simulate_chunk__independent_of_other_chunks():
    config = small_config()
    alone = chunk_bytes(dataset.simulate_chunk(config, 1))
    for index in (0, 3, 2):
        dataset.simulate_chunk(config, index)
    assert chunk_bytes(dataset.simulate_chunk(config, 1)) == alone
    # nor does a chunk depend on how many chunks the plan has
    longer = small_config(samples=3_000)
    assert chunk_bytes(dataset.simulate_chunk(longer, 1)) == alone
    # but chunks differ from one another and from another seed
    assert chunk_bytes(dataset.simulate_chunk(config, 0))[2] != alone[2]
    reseeded = config.replace(dataset={"seed": 12})
    assert chunk_bytes(dataset.simulate_chunk(reseeded, 1))[2] != alone[2]


# --- the default reciprocal prior gives the paper's raw MAE -------------------------------


@pytest.fixture(scope="module")
def default_store(tmp_path_factory) -> Path:
    path = tmp_path_factory.mktemp("prior") / "paper.zarr"
    generate(path, Config(prior=PriorConfig()))  # 20,000 rows of the paper's prior
    return path


def test_summarize__reciprocal_prior_raw_mae_matches_paper(default_store):
    summary = dataset.summarize(default_store)
    assert summary.samples == 20_000 and summary.noise_only_rows == 20_000
    raw_mae_31 = summary.mae_m[3]
    assert raw_mae_31 == pytest.approx(9.84e-3, abs=0.5e-3)  # paper: 9.857 mm
    assert summary.noise_only_mae_m[3] == pytest.approx(1.6e-3, abs=0.15e-3)
    # multipath biases depth the same way at every frequency, noise falls as 1/f: MAE decreases with f
    assert list(summary.mae_m) == sorted(summary.mae_m, reverse=True)


def test_summarize__noise_only_mae_matches_folded_normal_expectation(default_store):
    """Independent method: E|N(b, s^2)| per row from the exact tap moments and the noiseless bias b."""
    summary = dataset.summarize(default_store)
    config = dataset.store_config(dataset.open_store(default_store))
    theta = dataset.open_store(default_store)["theta"][:]
    freqs = np.asarray(config.frequencies_hz)
    mean, cov = MomentSensor(config).quadrature_moments(theta, multipath=False)
    gamma = np.hypot(mean[..., 0], mean[..., 1])
    perpendicular = np.stack([-mean[..., 1], mean[..., 0]], -1) / gamma[..., None]
    sigma = np.sqrt(np.einsum("...i,...ij,...j->...", perpendicular, cov, perpendicular)) / gamma * 3e8 / (
        4 * np.pi * freqs)
    quiet = config.replace(simulator={"noise_scale": 0.0})
    bias = MomentSensor(quiet).measure(theta, np.random.default_rng(0), multipath=False)[0] - theta[:, :1]
    folded = sigma * np.sqrt(2 / np.pi) * np.exp(-(bias**2) / (2 * sigma**2)) + bias * (
        1 - 2 * stats.norm.cdf(-bias / sigma))
    expected = folded.mean(0)
    standard_error = np.sqrt((sigma**2 + bias**2 - folded**2).sum(0)) / theta.shape[0]
    np.testing.assert_array_less(np.abs(np.array(summary.noise_only_mae_m) - expected), 5 * standard_error)


def test_prior_config__no_multipath_fraction_keeps_old_hashes_and_round_trips():
    from mpi_lidar.config import config_from_json, config_json

    assert "no_multipath_fraction" not in config_json(Config()), "the paper's prior hashes as before"
    mixed = Config().replace(prior={"no_multipath_fraction": 0.5})
    assert '"no_multipath_fraction":0.5' in config_json(mixed)
    assert config_from_json(config_json(mixed)) == mixed
    assert config_from_json(config_json(Config())).prior.no_multipath_fraction == 0.0


# --- the d_AS distribution ----------------------------------------------------------------------------------

# SHA-256 of chunk 0 (features, theta) of the quick preset as it was simulated before
# PriorConfig.d_as_distribution existed (20,000 rows in chunks of 5,000, d_AS uniform over 1.4-2.4 m): a
# regression anchor that the uniform prior still draws the very same numbers, so stored datasets keep their
# bytes. (The features pass through libm; a platform whose exp/sin round otherwise would differ.)
QUICK_CHUNK0_FEATURES_SHA256 = "e51a7da322080301ff35f4623468b773f7a7c3638120bf5d14298e8a0a75eca9"
QUICK_CHUNK0_THETA_SHA256 = "c66d6279738f808e738aac010fdcae1892d2cbca44deb65f5b49e26a54dd4484"


def test_simulate_chunk__uniform_prior_keeps_the_bytes_of_earlier_datasets():
    import hashlib

    config = Config(prior=PriorConfig(), dataset={"samples": 20_000, "chunk_rows": 5_000})
    chunk = dataset.simulate_chunk(config, 0)
    assert hashlib.sha256(chunk.theta.tobytes()).hexdigest() == QUICK_CHUNK0_THETA_SHA256
    assert hashlib.sha256(chunk.features.tobytes()).hexdigest() == QUICK_CHUNK0_FEATURES_SHA256


@pytest.mark.parametrize("scheme", sorted(SCHEMES))
def test_sample_theta__log_uniform_d_as_is_the_uniform_draw_mapped_to_log_scale(scheme):
    # Both distributions take the same single uniform draw for d_AS: u = (d_uniform - lo) / (hi - lo), and the
    # log-uniform d_AS is lo (hi / lo)^u; every other column is the very same draw.
    low, high = 0.5, 12.0
    uniform = sample_theta(PriorConfig(scheme=scheme, d_as_m=(low, high)), N, np.random.default_rng(8))
    log_uniform = sample_theta(PriorConfig(scheme=scheme, d_as_m=(low, high), d_as_distribution="log_uniform"), N,
                               np.random.default_rng(8))
    u = (column(uniform, "d_as_m") - low) / (high - low)
    np.testing.assert_allclose(column(log_uniform, "d_as_m"), low * (high / low) ** u, rtol=1e-12, atol=0)
    np.testing.assert_array_equal(log_uniform[:, 1:], uniform[:, 1:])


def test_sample_theta__log_uniform_d_as_fills_every_octave_alike():
    low, high = 0.5, 8.0  # four octaves
    d_as = column(sample_theta(PriorConfig(d_as_m=(low, high), d_as_distribution="log_uniform"), N,
                               np.random.default_rng(9)), "d_as_m")
    assert d_as.min() >= low and d_as.max() <= high
    assert stats.kstest(np.log(d_as), stats.uniform(np.log(low), np.log(high / low)).cdf).pvalue > KS_ALPHA
    counts, _ = np.histogram(d_as, [0.5, 1.0, 2.0, 4.0, 8.0])
    assert np.all(np.abs(counts - N / 4) <= 5 * np.sqrt(N / 4 * 3 / 4))  # binomial, 5 sigma
