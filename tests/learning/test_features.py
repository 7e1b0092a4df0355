"""Model inputs built column by column into one float32 array: the same bits as one float64 matrix rounded at
the end, whichever rows a thread fills."""

from __future__ import annotations

import numpy as np
import pytest

from mpi_lidar.config import Config
from mpi_lidar.errors import MpiLidarError
from mpi_lidar.learning.features import AMPLITUDE_FLOOR_V2, FeatureSpec, weighted_depth

FREQUENCIES = Config().frequencies_hz


def _float64_matrix(spec: FeatureSpec, raw: np.ndarray, geometry: np.ndarray | None) -> np.ndarray:
    """The inputs as one float64 matrix of every feature, rounded to float32 once at the end."""
    f = spec.n_freq
    columns = [raw.astype(np.float64)]
    if spec.feature_set == "engineered":
        depth = raw[:, :f].astype(np.float64)
        amplitude = np.maximum(raw[:, f:].astype(np.float64), AMPLITUDE_FLOOR_V2)
        columns += [depth[:, :-1] - depth[:, -1:], amplitude[:, :-1] / amplitude[:, -1:],
                    weighted_depth(raw, spec.frequencies_hz)[:, None], np.log(amplitude[:, -1:])]
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


@pytest.mark.parametrize("feature_set", ["raw", "engineered"])
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
