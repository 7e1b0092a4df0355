"""The benchmark's rows: train and test rows simulated from independent seed streams, and their error."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from mpi_lidar.config import Config
from mpi_lidar.learning.evaluate import error_metrics
from mpi_lidar.learning.features import FeatureSpec
from mpi_lidar.simulation.dataset import seeded_rng, simulate_rows

# Seed streams of the benchmark (under the configured dataset seed): train and test never share one.
TRAIN_STREAM, TEST_STREAM = 101, 202


@dataclass(frozen=True)
class Sample:
    """Simulated rows: raw measurements (n, 2F) [m, V^2], the true depth d_AS (n,) [m], theta (n, 6)."""

    raw: NDArray[np.float32]
    target: NDArray[np.float64]
    theta: NDArray[np.float64]

    def __len__(self) -> int:
        return self.target.size

    def head(self, n: int) -> Sample:
        return Sample(self.raw[:n], self.target[:n], self.theta[:n])

    def inputs(self, spec: FeatureSpec) -> tuple[NDArray[np.float32], NDArray[np.float64]]:
        """The model inputs and the training target of these rows under ``spec``."""
        return spec.transform(self.raw), spec.target(self.raw, self.target)


def simulate(config: Config, n: int, stream: int, noise_scale: float | None = None,
             d_as_m: tuple[float, float] | None = None) -> Sample:
    """n rows drawn from the configured prior and measured by its sensor, from seed stream ``stream``.

    ``noise_scale`` replaces the simulator's noise scale and ``d_as_m`` the prior's d_AS range [m]
    (e.g. an out-of-range test set); everything else is the configuration's.
    """
    if noise_scale is not None:
        config = config.replace(simulator={"noise_scale": noise_scale})
    if d_as_m is not None:
        config = config.replace(prior={"d_as_m": d_as_m})
    features, theta = simulate_rows(config, n, seeded_rng(config.dataset.seed, stream))
    return Sample(features, theta[:, 0].copy(), theta)


def mae(estimate: NDArray, truth: NDArray) -> float:
    """Mean absolute error over all rows (:func:`error_metrics`); NaN if any estimate is not finite. [m]"""
    metrics = error_metrics(estimate, truth)
    return metrics.mae_m if metrics.non_finite == 0 else float("nan")
