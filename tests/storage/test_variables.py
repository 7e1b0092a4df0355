"""The registry of store variables (mpi_lidar.storage.variables) and the reference page made from it."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from mpi_lidar.scans.scan import OPTIONAL_ARRAYS, Scan
from mpi_lidar.scans.store import ARRAY_METADATA, COORDINATE_ARRAYS
from mpi_lidar.storage import variables
from mpi_lidar.storage.variables import CORRECTED, DATASET, SCAN, VARIABLES, Store

pytestmark = pytest.mark.unit

ROOT = Path(__file__).resolve().parents[2]


def test_reference_page__is_generated_from_the_registry():
    page = ROOT / variables.REFERENCE_PAGE
    assert page.exists() and page.read_text() == variables.reference_markdown(), (
        f"{variables.REFERENCE_PAGE} is out of date with mpi_lidar/storage/variables.py; regenerate it with "
        f"{variables.REGENERATE}")


def test_registry__each_variable_once_per_store_with_known_kinds():
    keys = [(v.store, v.name) for v in VARIABLES]
    assert len(keys) == len(set(keys))
    assert all(v.kind in variables.KIND_NAMES and v.units and v.long_name and v.dims for v in VARIABLES)
    assert all(v.dtype == "as given" or np.dtype(v.dtype).kind == v.kind for v in VARIABLES)
    assert {v.store for v in VARIABLES} == set(Store)


def test_registry__scan_store_declares_every_array_of_a_scan():
    arrays = {"depth", "amplitude", "taps", *OPTIONAL_ARRAYS}
    assert arrays <= set(SCAN) and arrays <= set(Scan.__dataclass_fields__)
    assert set(SCAN) - arrays == set(COORDINATE_ARRAYS) == {"frequency_hz", "y", "x"}
    assert list(OPTIONAL_ARRAYS) == ["azimuth_rad", "elevation_rad", "ray_directions", "reference_depth",
                                     "reference_mask", "taps"]


def test_registry__attributes_the_stores_have_always_written():
    """units and long_name as the stores wrote them before the registry: the stores' bytes do not change."""
    assert ARRAY_METADATA == {
        "depth": ("m", "measured range along the ray"),
        "amplitude": ("V^2", "measured amplitude"),
        "taps": ("V^2", "demodulation taps"),
        "azimuth_rad": ("rad", "azimuth of the pixel column"),
        "elevation_rad": ("rad", "elevation of the pixel row"),
        "ray_directions": ("1", "unit ray direction (x left, y up, z forward)"),
        "reference_depth": ("m", "reference range along the ray"),
        "reference_mask": ("1", "reference region mask (1 where the reference holds)"),
        "frequency_hz": ("Hz", "modulation frequency"),
        "y": ("1", "pixel row"),
        "x": ("1", "pixel column"),
        "corrected_depth": ("m", "corrected range along the ray"),
        "flags": ("1", "what was done to the pixel"),
        "multipath_bias_m": ("m", "expected multipath bias (geometry gate)"),
        # new arrays (2026-11-25): those above keep what they were
        "measured_depth": ("m", "measured range along the ray at the highest frequency"),
        "unwrap_confidence": ("1", "posterior probability of the chosen wrap counts"),
        "estimate": ("1", "which estimate the corrected depth is"),
        "depth_uncertainty": ("m", "1-sigma uncertainty of the corrected depth"),
        "second_return_depth": ("m", "range of the weaker of two returns (flag two_returns)"),
        "second_return_share": ("1", "share of the light of the weaker of two returns (flag two_returns)"),
        "second_return_uncertainty": ("m",
                                      "1-sigma uncertainty of the weaker of two returns' range (flag two_returns)"),
    }
    assert {name: (v.units, v.long_name) for name, v in CORRECTED.items()}.items() <= ARRAY_METADATA.items()
    assert {name: v.dims for name, v in DATASET.items()} == {
        "features": ("sample", "feature"), "target": ("sample",), "theta": ("sample", "parameter"),
        "split": ("sample",), "chunk_done": ("chunk",), "chunk_sha256": ("chunk", "array", "byte")}


def test_variable__dtype_problem_names_the_kind():
    assert SCAN["depth"].dtype_problem(np.float64) is None
    assert SCAN["depth"].dtype_problem(np.int32) == "depth must be floating point, got int32"
    assert SCAN["reference_mask"].dtype_problem(np.uint8) == "reference_mask must be boolean, got uint8"
    assert SCAN["taps"].shape({"frequency": 2, "y": 3, "x": 4, **variables.FIXED_SIZES}) == (2, 4, 3, 4)
