"""Small models trained in this process in a second, for correction and output tests (no cluster)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from mpi_lidar.config import Config, PriorConfig
from mpi_lidar.learning.features import FeatureSpec, synthetic_geometry
from mpi_lidar.learning.model import save_model
from mpi_lidar.learning.model_card import DatasetCard
from mpi_lidar.learning.train import model_card, train_arrays
from mpi_lidar.simulation.dataset import seeded_rng, simulate_rows
from mpi_lidar.simulation.sampling import THETA_NAMES


def tiny_model(out: Path, geometric: bool = True, feature_set: str = "engineered", rows: int = 3_000,
               rounds: int = 30, config: Config | None = None) -> Path:
    """A residual model of ``feature_set`` (with the geometric inputs if ``geometric``) on rows simulated from
    ``config`` (default: the paper's prior, d_AS 1.4-2.4 m, the range the tests' scans and range rules use)."""
    config = config or Config(prior=PriorConfig())
    spec = FeatureSpec(config.frequencies_hz, feature_set, "residual", geometric)
    raw, theta = simulate_rows(config, rows, seeded_rng(config.dataset.seed, 0))
    geometry = synthetic_geometry(theta, THETA_NAMES, config.dataset.seed, np.arange(rows))
    params = {"max_depth": 4}
    fitted = train_arrays(spec.transform(raw, geometry), spec.target(raw, theta[:, 0]), params, rounds, None)
    card = model_card(spec, DatasetCard.from_config(config, path="in memory"), params, fitted, workers=0)
    return save_model(out, fitted.booster, card)
