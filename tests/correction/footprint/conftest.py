"""A tiny model with geometric inputs, trained once per module of the footprint tests."""

from __future__ import annotations

import pytest

from mpi_lidar.learning.model import load_model
from tests.model_factory import tiny_model


@pytest.fixture(scope="module")
def tiny_geometric_model_dir(tmp_path_factory):
    return tiny_model(tmp_path_factory.mktemp("calibration") / "model", geometric=True)


@pytest.fixture(scope="module")
def tiny_geometric_model(tiny_geometric_model_dir):
    return load_model(tiny_geometric_model_dir)
