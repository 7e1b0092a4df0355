from __future__ import annotations

import numpy as np
import pytest

from mpi_lidar.config import Config


@pytest.fixture
def config() -> Config:
    return Config()


@pytest.fixture
def rng() -> np.random.Generator:
    return np.random.default_rng(12345)
