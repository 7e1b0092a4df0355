"""The rows of a dataset: the sampling plan, the seed tree and the simulation of each chunk.

Chunk i draws its rows from a generator seeded by (seed, i) (:func:`seeded_rng`), so the bytes of a chunk are a
pure function of the configuration and its index.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import numpy as np
from numpy.typing import NDArray

from mpi_lidar.config import Config
from mpi_lidar.physics import SensorModel, make_sensor
from mpi_lidar.physics.demod import unambiguous_range
from mpi_lidar.physics.noise import unwrapped_rows
from mpi_lidar.simulation.sampling import sample_theta

SPLIT_CODES = {"train": 0, "test": 1}


@dataclass(frozen=True)
class SamplingPlan:
    """n rows in chunks of ``chunk_rows`` (the last one shorter), drawn from ``seed``."""

    samples: int
    chunk_rows: int
    seed: int

    @classmethod
    def from_config(cls, config: Config) -> SamplingPlan:
        d = config.dataset
        return cls(d.samples, d.chunk_rows, d.seed)

    @property
    def chunks(self) -> int:
        return -(-self.samples // self.chunk_rows)

    def rows_in(self, indices: list[int]) -> int:
        """How many rows the given chunks hold."""
        return sum(self.rows(i).stop - self.rows(i).start for i in indices)

    def rows(self, index: int) -> slice:
        if not 0 <= index < self.chunks:
            raise IndexError(f"chunk {index} outside 0..{self.chunks - 1}")
        return slice(index * self.chunk_rows, min((index + 1) * self.chunk_rows, self.samples))


@dataclass(frozen=True)
class Chunk:
    features: NDArray[np.float32]
    target: NDArray[np.float64]
    theta: NDArray[np.float64]
    split: NDArray[np.uint8]


def seeded_rng(seed: int, *stream: int) -> np.random.Generator:
    """A generator for one stream of the seed tree: chunk i uses stream (i,)."""
    return np.random.default_rng(np.random.SeedSequence(seed, spawn_key=stream))


@lru_cache(maxsize=8)
def cached_sensor(config: Config) -> SensorModel:
    return make_sensor(config)


def simulate_rows(config: Config, n: int, rng: np.random.Generator) -> tuple[NDArray[np.float32], NDArray[np.float64]]:
    """n rows drawn from the configured prior and measured by its sensor, from ``rng``: the features (n, 2F)
    (depths then amplitudes, float32) and theta (n, 6); the true depth d_AS is theta's first column. [m, V^2]

    Where the prior reaches ranges at which a frequency's depth wraps (:func:`prior_wraps`), the depths are
    unwrapped into one range as correction unwraps a scan's (:func:`mpi_lidar.physics.noise.unwrapped_rows`),
    so the model learns from what it will be given.
    """
    theta = sample_theta(config.prior, n, rng)
    depth, amplitude = cached_sensor(config).measure(theta, rng)
    rows = np.concatenate([depth, amplitude], axis=1).astype(np.float32)
    if prior_wraps(config):
        rows, _ = unwrapped_rows(rows, config.frequencies_hz, config.sensor)
    return rows, theta


# Share of the highest frequency's unambiguous range that a prior's longest path may reach and still count as
# never wrapping: a margin for the noise of the farthest, weakest rows.
NO_WRAP_SHARE = 0.9


def prior_wraps(config: Config) -> bool:
    """Whether the prior's longest path (farthest d_AS plus longest d_AB) reaches 90 % of the smallest
    unambiguous range c / 2f: only then can a measured depth wrap. A prior that cannot wrap is not unwrapped,
    so its datasets stay byte for byte what they were before unwrapping existed. [1]"""
    longest_m = config.prior.d_as_m[1] + config.prior.d_ab_m[1]
    shortest_range_m = float(unambiguous_range(max(config.frequencies_hz), config.sensor.speed_of_light_m_per_s))
    return longest_m >= NO_WRAP_SHARE * shortest_range_m


def simulate_chunk(config: Config, index: int) -> Chunk:
    """Draw, simulate and split chunk ``index`` of the configured plan; a pure function of both."""
    plan = SamplingPlan.from_config(config)
    rows = plan.rows(index)
    n = rows.stop - rows.start
    rng = seeded_rng(plan.seed, index)
    features, theta = simulate_rows(config, n, rng)
    split = np.zeros(n, dtype=np.uint8)
    split[rng.permutation(n)[: round(n * config.dataset.test_fraction)]] = SPLIT_CODES["test"]
    return Chunk(features=features, target=theta[:, 0].copy(), theta=theta, split=split)
