"""Amplitudes in the scanner's unit, read in V^2 without a copy: the same values as the divided copy they replace."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from mpi_lidar.correction import CorrectionOptions, correct_scan
from mpi_lidar.correction.amplitude_in_v2 import AmplitudeInV2
from mpi_lidar.learning.model import load_model
from mpi_lidar.scans.store import read_scan, write_scan
from mpi_lidar.scans.stored_map import StoredMap
from tests.scan_factory import two_path_scan

pytestmark = pytest.mark.unit

UNITS_PER_V2 = 4000.0


@pytest.fixture
def scan_in_units():
    scan = two_path_scan("units", height=24, width=32)
    return replace(scan, amplitude=(np.asarray(scan.amplitude) * UNITS_PER_V2).astype(np.float32))


def divided(scan) -> np.ndarray:
    """The copy :class:`AmplitudeInV2` stands in for."""
    return (np.asarray(scan.amplitude) / UNITS_PER_V2).astype(np.float32)


@pytest.mark.parametrize("stored", [False, True])
def test_amplitude_in_v2__reads_like_the_divided_maps(scan_in_units, tmp_path, stored):
    scan = scan_in_units
    if stored:
        write_scan(scan, tmp_path / "units.scan.zarr")
        scan = read_scan(tmp_path / "units.scan.zarr", stored_above_bytes=0)
        assert isinstance(scan.amplitude, StoredMap)
    expected = divided(scan)
    maps = AmplitudeInV2(scan.amplitude, UNITS_PER_V2)
    assert maps.shape == expected.shape and maps.dtype == np.float32 and maps.in_store is stored
    ys, xs = np.array([0, 5, 23, 7]), np.array([31, 0, 4, 7])
    for key in [(slice(None), slice(3, 9)), (2, slice(0, 24), slice(4, 10)), (slice(None), ys, xs)]:
        np.testing.assert_array_equal(maps[key], expected[key])
    np.testing.assert_array_equal(np.asarray(maps), expected)
    assert replace(scan, amplitude=maps).in_memory() is not stored


def test_correct_scan__a_scan_in_the_scanner_s_unit_corrects_as_its_divided_copy(scan_in_units, pixelwise_model):
    model = load_model(pixelwise_model)
    in_units = correct_scan(scan_in_units, model, CorrectionOptions(amplitude_scale=UNITS_PER_V2))
    copied = correct_scan(replace(scan_in_units, amplitude=divided(scan_in_units)), model,
                          CorrectionOptions(amplitude_scale=1.0))
    for name in ("depth", "flags", "estimate", "uncertainty_m"):
        np.testing.assert_array_equal(getattr(in_units, name), getattr(copied, name), err_msg=name)
    assert in_units.amplitude_units_per_v2 == UNITS_PER_V2
