"""Fixtures of the reporting tests: a tiny model, an archived scan and a rendered board."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from mpi_lidar.config import Config
from mpi_lidar.scans.store import write_scan
from mpi_lidar.simulation.scenes import cornered_board, render
from tests.model_factory import tiny_model
from tests.scan_factory import two_path_scan


@pytest.fixture(scope="package")
def model_dir(tmp_path_factory) -> Path:
    return tiny_model(tmp_path_factory.mktemp("model") / "model")


@pytest.fixture(scope="package")
def archived(tmp_path_factory):
    """A scan as an archive holds it: geometry, no reference depth."""
    scan = replace(two_path_scan("archived"), reference_depth=None, reference_mask=None)
    return scan, write_scan(scan, tmp_path_factory.mktemp("scans") / "archived.scan.zarr")


@pytest.fixture(scope="package")
def board_store(tmp_path_factory) -> Path:
    scan = render(cornered_board(height=40, width=56), Config(), np.random.default_rng(3))
    return write_scan(scan, tmp_path_factory.mktemp("scans") / "board.scan.zarr")
