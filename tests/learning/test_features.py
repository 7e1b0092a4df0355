"""Model inputs built column by column into one float32 array: the same bits as one float64 matrix rounded at
the end, whichever rows a thread fills."""

from __future__ import annotations

import numpy as np
import pytest

from mpi_lidar.config import Config
from mpi_lidar.errors import MpiLidarError
from mpi_lidar.learning.features import AMPLITUDE_FLOOR_V2, FeatureSpec, weighted_depth
from mpi_lidar.physics.transport import two_path_phasors

pytestmark = pytest.mark.unit

FREQUENCIES = Config().frequencies_hz


def _float64_matrix(spec: FeatureSpec, raw: np.ndarray, geometry: np.ndarray | None) -> np.ndarray:
    """The inputs as one float64 matrix of every feature, rounded to float32 once at the end."""
    f = spec.n_freq
    columns = [raw.astype(np.float64)] if spec.feature_set in ("raw", "engineered") else []
    if spec.feature_set != "raw":
        depth = raw[:, :f].astype(np.float64)
        amplitude = np.maximum(raw[:, f:].astype(np.float64), AMPLITUDE_FLOOR_V2)
        weighted = weighted_depth(raw, spec.frequencies_hz)[:, None]
        columns += [depth[:, :-1] - depth[:, -1:], amplitude[:, :-1] / amplitude[:, -1:],
                    weighted if spec.feature_set == "engineered" else weighted - depth[:, -1:],
                    np.log(amplitude[:, -1:])]
    if spec.feature_set == "physical":
        columns.append(np.log(amplitude[:, -1:] * depth[:, -1:] ** 2))
    if spec.geometric:
        columns.append(geometry.astype(np.float64))
    return np.concatenate(columns, axis=1).astype(np.float32)


def _hostile_rows(rng: np.random.Generator, n: int) -> np.ndarray:
    """Raw rows (n, 8) float32 with ordinary values and, in some rows, NaN, zero, negative and huge ones."""
    raw = np.concatenate([rng.uniform(1.3, 2.5, (n, 4)), rng.lognormal(-4, 2, (n, 4))], axis=1).astype(np.float32)
    picks = rng.integers(0, n, 40)
    raw[picks[:10], 1] = np.nan
    raw[picks[10:20], 5] = 0.0
    raw[picks[20:30], 7] = -1e-3
    raw[picks[30:], 3] = 3e38
    return raw


@pytest.mark.parametrize("feature_set", ["raw", "engineered", "range_free", "physical"])
@pytest.mark.parametrize("geometric", [False, True])
def test_transform__every_column_rounded_once_from_float64(feature_set, geometric):
    rng = np.random.default_rng(7)
    spec = FeatureSpec(FREQUENCIES, feature_set, "residual", geometric)
    raw = _hostile_rows(rng, 5_000)
    geometry = np.column_stack([rng.uniform(0, 1, 5_000), rng.uniform(0, 0.15, 5_000)]) if geometric else None
    with np.errstate(all="ignore"):
        expected = _float64_matrix(spec, raw, geometry)
        found = spec.transform(raw, geometry)
    assert found.dtype == np.float32 and found.shape == (5_000, len(spec.names))
    assert found.tobytes() == expected.tobytes()


def test_transform_into__row_ranges_filled_apart_make_the_whole_transform():
    rng = np.random.default_rng(8)
    spec = FeatureSpec(FREQUENCIES, "engineered", "residual", True)
    raw = _hostile_rows(rng, 3_001)
    geometry = np.column_stack([rng.uniform(0, 1, 3_001), rng.uniform(0, 0.15, 3_001)])
    out = np.full((3_001, len(spec.names)), -7.0, dtype=np.float32)
    with np.errstate(all="ignore"):
        for rows in (slice(0, 1_000), slice(1_000, 1_001), slice(1_001, 3_001)):
            spec.transform_into(raw[rows], geometry[rows], out[rows])
        assert out.tobytes() == spec.transform(raw, geometry).tobytes()


def test_transform_into__refuses_missing_geometric_inputs_and_misshapen_rows():
    spec = FeatureSpec(FREQUENCIES, "engineered", "residual", True)
    out = np.empty((3, len(spec.names)), dtype=np.float32)
    with pytest.raises(MpiLidarError, match="needs them for every pixel"):
        spec.transform_into(np.ones((3, 8), dtype=np.float32), None, out)
    with pytest.raises(MpiLidarError, match=r"shape \(n, 8\)"):
        spec.transform(np.ones((3, 7), dtype=np.float32), np.zeros((3, 2)))


# --- range_free: no input carries the absolute range -----------------------------------------------------------


def _two_path_raw(theta: np.ndarray) -> np.ndarray:
    """Noiseless raw rows (n, 8) of the two-path transport, depths unwrapped: d_AS plus each frequency's
    multipath phase bias arg(1 + (Gamma_M / Gamma_D) e^{i (phi_M - phi_D)}) over 4 pi f / c. [m, V^2]"""
    config = Config()
    c = config.sensor.speed_of_light_m_per_s
    gamma_d, phi_d, gamma_m, phi_m = two_path_phasors(theta, FREQUENCIES, config.sensor.gamma_r_v2, c)
    relative = 1 + gamma_m / gamma_d * np.exp(1j * (phi_m - phi_d))
    omega = 4 * np.pi * np.asarray(FREQUENCIES) / c
    depth = theta[:, :1] + np.angle(relative) / omega
    return np.hstack([depth, gamma_d * np.abs(relative)])


def test_transform__range_free_same_scene_at_1_m_and_5_m_with_equal_amplitudes_is_identical():
    # Direct amplitude gamma_r rho_SAS / d^2 and multipath ratio rho_SAB rho_ABA rho_BAS / rho_SAS kept equal:
    # 0.02 / 1^2 = 0.5 / 5^2 and 0.02 * 0.5 * 0.02 / 0.02 = 0.5 * 0.5 * 0.02 / 0.5 = 0.01; same d_AB.
    near = np.array([[1.0, 0.05, 0.02, 0.02, 0.5, 0.02], [1.0, 0.12, 0.02, 0.02, 0.5, 0.02]])
    far = np.array([[5.0, 0.05, 0.5, 0.5, 0.5, 0.02], [5.0, 0.12, 0.5, 0.5, 0.5, 0.02]])
    raw_near, raw_far = _two_path_raw(near), _two_path_raw(far)
    np.testing.assert_allclose(raw_far[:, 4:], raw_near[:, 4:], rtol=1e-12, atol=0)  # the amplitudes agree
    spec = FeatureSpec(FREQUENCIES, "range_free", "residual")
    np.testing.assert_allclose(spec.transform(raw_far), spec.transform(raw_near), rtol=1e-6, atol=1e-9)
    # the residual target agrees too; the engineered inputs carry the 4 m between the two
    np.testing.assert_allclose(spec.target(raw_far, far[:, 0]), spec.target(raw_near, near[:, 0]), rtol=0,
                               atol=1e-12)
    engineered = FeatureSpec(FREQUENCIES, "engineered", "residual")
    weighted = engineered.names.index("weighted_depth")
    np.testing.assert_allclose(engineered.transform(raw_far)[:, weighted] - engineered.transform(raw_near)[:, weighted],
                               4.0, rtol=0, atol=1e-6)


def test_transform__physical_inputs_of_one_surface_at_1_m_and_5_m_differ_only_in_the_noise_level():
    # The same surface (albedo 0.5, rho_ABA 0.3, d_AB 5 and 12 cm) at 1 m and at 5 m: the multipath ratio is the
    # same, the amplitude 25 times lower; the albedo column (A d^2) agrees, the log amplitude differs by ln 25.
    near = np.array([[1.0, 0.05, 0.5, 0.5, 0.3, 0.5], [1.0, 0.12, 0.5, 0.5, 0.3, 0.5]])
    far = near.copy()
    far[:, 0] = 5.0
    spec = FeatureSpec(FREQUENCIES, "physical", "residual")
    x_near, x_far = spec.transform(_two_path_raw(near)), spec.transform(_two_path_raw(far))
    level, albedo = spec.names.index("log_amplitude_31.25MHz"), spec.names.index("log_albedo_31.25MHz")
    others = [i for i in range(len(spec.names)) if i not in (level, albedo)]
    np.testing.assert_allclose(x_far[:, others], x_near[:, others], rtol=1e-5, atol=1e-7)
    np.testing.assert_allclose(x_near[:, level] - x_far[:, level], np.log(25.0), rtol=1e-6)
    # A d^2 with the measured depth: its multipath bias (a few mm) weighs 2 bias / d in the log, more at 1 m
    np.testing.assert_allclose(x_near[:, albedo], x_far[:, albedo], rtol=0, atol=0.03)


@pytest.mark.parametrize("feature_set", ["raw", "engineered", "range_free", "physical"])
@pytest.mark.parametrize("geometric", [False, True])
def test_names__as_many_as_the_transform_has_columns(feature_set, geometric):
    spec = FeatureSpec(FREQUENCIES, feature_set, "residual", geometric)
    rng = np.random.default_rng(10)
    raw = np.concatenate([rng.uniform(0.5, 12.0, (40, 4)), rng.lognormal(-6, 2, (40, 4))], 1).astype(np.float32)
    geometry = np.zeros((40, 2)) if geometric else None
    assert spec.transform(raw, geometry).shape == (40, len(spec.names))
    assert len(set(spec.names)) == len(spec.names)
    expected = {"raw": 8, "engineered": 16, "range_free": 8, "physical": 9}[feature_set] + 2 * geometric
    assert len(spec.names) == expected


def test_names__range_free_are_relative_to_the_highest_frequency():
    names = FeatureSpec(FREQUENCIES, "range_free", "residual").names
    assert names == ["depth_12.5MHz_minus_31.25MHz", "depth_18.75MHz_minus_31.25MHz", "depth_25MHz_minus_31.25MHz",
                     "amplitude_12.5MHz_over_31.25MHz", "amplitude_18.75MHz_over_31.25MHz",
                     "amplitude_25MHz_over_31.25MHz", "weighted_depth_minus_31.25MHz", "log_amplitude_31.25MHz"]


@pytest.mark.parametrize("geometric", [False, True])
def test_transform__range_free_dask_and_numpy_agree(geometric):
    import dask.array as da

    rng = np.random.default_rng(11)
    spec = FeatureSpec(FREQUENCIES, "range_free", "residual", geometric)
    raw = np.concatenate([rng.uniform(0.5, 12.0, (1_000, 4)), rng.lognormal(-6, 2, (1_000, 4))], 1).astype(np.float32)
    geometry = np.column_stack([rng.uniform(0, 1, 1_000), rng.uniform(0, 0.15, 1_000)]) if geometric else None
    lazy = spec.transform(da.from_array(raw, chunks=(300, 4)),
                          da.from_array(geometry, chunks=(300, 2)) if geometric else None)
    found = lazy.compute()
    assert found.dtype == np.float32
    assert found.tobytes() == spec.transform(raw, geometry).tobytes()


def test_feature_spec__range_free_refuses_the_absolute_target_in_one_line():
    with pytest.raises(MpiLidarError, match="range_free feature set holds no absolute depth, so it cannot") as caught:
        FeatureSpec(FREQUENCIES, "range_free", "absolute")
    assert "\n" not in str(caught.value) and "'residual'" in str(caught.value)
