"""Unwrapped depths put in as the maps are read: every read is that of the maps with them put in, and a scan
corrected so is the scan corrected from a copy of its unwrapped maps, to the last bit."""

from __future__ import annotations

from typing import cast

import numpy as np
import pytest
import zarr

from mpi_lidar.config import Config
from mpi_lidar.correction import CorrectionOptions, correct_scan
from mpi_lidar.correction import result as result_module
from mpi_lidar.correction import tiles as tiles_module
from mpi_lidar.correction.result import COUNT_CHUNK_PIXELS, code_counts
from mpi_lidar.correction.tiles import row_tiles, scan_tiles
from mpi_lidar.correction.unwrapped_depth import UnwrappedDepth
from mpi_lidar.learning.model import load_model
from mpi_lidar.reporting.correction_notes import correction_notes
from mpi_lidar.scans.scan import Scan
from mpi_lidar.scans.store import read_scan, write_scan
from mpi_lidar.scans.stored_map import StoredMap
from mpi_lidar.simulation.scenes import cornered_board, render
from tests.model_factory import tiny_model
from tests.scan_factory import two_path_scan

pytestmark = pytest.mark.unit

KEYS = [
    (slice(None), slice(3, 9)),  # a tile of rows, as correction reads one
    (slice(None),),
    (-1, slice(0, 24), slice(5, 20)),  # a box of one frequency, as the albedo reads one
    (1, 7, 4),
    (slice(None), 7, slice(2, 30)),
    (slice(None, None, -1), slice(10, 12)),
    (slice(1, 3), slice(20, 40), slice(0, 32)),  # rows past the end, as a slice allows
]


@pytest.fixture(scope="module")
def stored_store(tmp_path_factory):
    return write_scan(two_path_scan("stored", 24, 32, seed=3), tmp_path_factory.mktemp("stored") / "s.scan.zarr")


def _moved(shape: tuple[int, int, int], rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    f, h, w = shape
    pixels = np.sort(rng.choice(h * w, size=h * w // 5, replace=False))
    return pixels, rng.uniform(5.0, 20.0, (pixels.size, f)).astype(np.float32)


@pytest.mark.parametrize("in_store", [False, True], ids=["in-memory", "stored"])
def test_unwrapped_depth__every_read_is_that_of_the_maps_with_the_moved_depths_put_in(stored_store, in_store):
    scan = read_scan(stored_store, stored_above_bytes=0 if in_store else float("inf"))
    measured = np.array(scan.depth)
    pixels, depths = _moved(measured.shape, np.random.default_rng(1))
    unwrapped = UnwrappedDepth(scan.depth, pixels, depths)
    expected = measured.reshape(measured.shape[0], -1).copy()
    expected[:, pixels] = depths.T
    expected = expected.reshape(measured.shape)
    np.testing.assert_array_equal(unwrapped.whole(), expected)
    np.testing.assert_array_equal(np.asarray(unwrapped), expected)
    for key in KEYS:
        np.testing.assert_array_equal(unwrapped[key], expected[key], err_msg=str(key))
    ys, xs = np.divmod(np.concatenate([pixels[:7], [0, 5, 767]]), 32)  # moved pixels and others
    np.testing.assert_array_equal(unwrapped[:, ys, xs], expected[:, ys, xs])
    np.testing.assert_array_equal(unwrapped[-1, ys, xs], expected[-1, ys, xs])
    np.testing.assert_array_equal(np.asarray(scan.depth), measured)  # the maps as measured stay as they were


def test_unwrapped_depth__without_moved_pixels_reads_the_maps():
    measured = np.arange(2 * 3 * 4, dtype=np.float32).reshape(2, 3, 4)
    unwrapped = UnwrappedDepth(measured, np.zeros(0, dtype=np.intp), np.zeros((0, 2), dtype=np.float32))
    np.testing.assert_array_equal(unwrapped[:, 1:3], measured[:, 1:3])
    np.testing.assert_array_equal(unwrapped[:, np.array([0, 2]), np.array([3, 1])], measured[:, [0, 2], [3, 1]])
    with pytest.raises(IndexError):
        unwrapped[:, ::2]


def test_correct_scan__moved_depths_put_in_as_read_correct_as_a_copy_of_the_unwrapped_maps(tmp_path, monkeypatch):
    board = render(cornered_board(height=60, width=80), Config(), np.random.default_rng(4))
    model = load_model(tiny_model(tmp_path / "model", geometric=True))
    as_read = correct_scan(board, model, CorrectionOptions())
    moved = []

    class CopiedWhole(UnwrappedDepth):
        """Every read from a copy of the whole unwrapped maps, as correction read them before."""

        def __init__(self, measured, pixels, depths):
            super().__init__(measured, pixels, depths)
            moved.append(pixels.size)

        def __getitem__(self, key):
            return self.whole()[key]

    monkeypatch.setattr(tiles_module, "UnwrappedDepth", CopiedWhole)
    copied = correct_scan(board, model, CorrectionOptions())
    assert moved and moved[0] > 0, "the scan must have depths that took a wrap count"
    for name in ("depth", "flags", "estimate", "uncertainty_m", "measured_depth", "multipath_bias_m"):
        assert getattr(copied, name).tobytes() == getattr(as_read, name).tobytes(), name
    assert correction_notes(copied) == correction_notes(as_read)


def test_scan_tiles__a_stored_scan_tiles_whole_rows_within_its_bands(monkeypatch):
    monkeypatch.setattr("mpi_lidar.scans.stored_map.BAND_VALUES", 2 * 32 * 10)  # two chunk rows of 5 a band
    array = zarr.create_array(store={}, shape=(2, 24, 32), chunks=(1, 5, 32), dtype="float32")
    stored = StoredMap(array, 1, np.float32)
    scan = Scan("stored", (1e7, 2e7), depth=cast("np.ndarray", stored), amplitude=cast("np.ndarray", stored))
    bands = stored.row_bands()
    assert [(b.start, b.stop) for b in bands] == [(0, 10), (10, 20), (20, 24)]
    tiles = scan_tiles(scan, 32 * 3)  # three rows a tile: row_tiles alone would read rows 9-12 across two bands
    covered = np.concatenate([np.arange(t.start, t.stop) for t in tiles])
    np.testing.assert_array_equal(covered, np.arange(24 * 32))
    for tile in tiles:
        rows = range(tile.start // 32, tile.stop // 32)
        assert tile.start % 32 == 0 and tile.stop % 32 == 0 and 0 < len(rows) <= 3
        assert any(b.start <= rows.start and rows.stop <= b.stop for b in bands), f"rows {rows} in one band"
    assert scan_tiles(two_path_scan("memory", 24, 32), 32 * 3) == row_tiles(24, 32, 32 * 3)


def test_code_counts__chunks_count_what_bincount_counts(monkeypatch):
    codes = np.random.default_rng(2).integers(0, 7, (13, 11)).astype(np.uint8)
    monkeypatch.setattr(result_module, "COUNT_CHUNK_PIXELS", 10)
    np.testing.assert_array_equal(code_counts(codes, 9), np.bincount(codes.ravel(), minlength=9))
    assert COUNT_CHUNK_PIXELS >= 2**16
