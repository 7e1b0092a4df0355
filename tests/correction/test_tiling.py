"""Row tiles: a scan corrected tile by tile is the scan corrected at once, to the last bit."""

from __future__ import annotations

import tracemalloc

import numpy as np
import pytest

from mpi_lidar.config import Config
from mpi_lidar.correction import CorrectionOptions, Flag, correct_scan
from mpi_lidar.correction.correct import row_tiles
from mpi_lidar.learning.model import load_model
from mpi_lidar.simulation.scenes import cornered_board, render
from tests.model_factory import tiny_model


@pytest.fixture(scope="module")
def board():
    return render(cornered_board(height=60, width=80), Config(), np.random.default_rng(4))


@pytest.fixture(scope="module", params=[True, False], ids=["geometric", "pixel-wise"])
def model(request, tmp_path_factory):
    return load_model(tiny_model(tmp_path_factory.mktemp("model") / "model", geometric=request.param))


def test_row_tiles__whole_rows_cover_every_pixel_once():
    tiles = row_tiles(7, 5, 12)  # 12 pixels: two rows of 5 per tile
    assert [(t.start, t.stop) for t in tiles] == [(0, 10), (10, 20), (20, 30), (30, 35)]
    assert [(t.start, t.stop) for t in row_tiles(3, 10, 1)] == [(0, 10), (10, 20), (20, 30)]  # at least a row
    assert [(t.start, t.stop) for t in row_tiles(3, 10, 10**6)] == [(0, 30)]


@pytest.mark.parametrize("gate", ["geometry", "all", "consistency"])
def test_correct_scan__tiled_equals_untiled_to_the_last_bit(board, model, gate):
    whole = correct_scan(board, model, CorrectionOptions(gate=gate, tile_pixels=10**7))
    assert whole.counts()["corrected"] > 0, "the comparison must cover corrected pixels"
    for tile_pixels in (80, 7 * 80 + 13, 1):  # one row, several rows and a remainder, a pixel (one row)
        tiled = correct_scan(board, model, CorrectionOptions(gate=gate, tile_pixels=tile_pixels))
        assert tiled.depth.dtype == whole.depth.dtype == np.float32
        assert tiled.depth.tobytes() == whole.depth.tobytes()
        assert tiled.flags.tobytes() == whole.flags.tobytes()
        assert (tiled.multipath_bias_m is None) == (whole.multipath_bias_m is None)
        if whole.multipath_bias_m is not None:
            assert tiled.multipath_bias_m.tobytes() == whole.multipath_bias_m.tobytes()
        assert tiled.notes == whole.notes


def test_correct_scan__geometry_gate_corrects_near_the_corner_and_says_what_it_cost(board, model):
    correction = correct_scan(board, model, CorrectionOptions(tile_pixels=800))
    counts = correction.counts()
    assert counts["corrected"] > 0 and counts["no_multipath"] > 0
    gated = correction.flags == Flag.NO_MULTIPATH
    np.testing.assert_array_equal(correction.depth[gated], board.depth[-1][gated])
    assert set(correction.cpu_s) == {"validity", "gate", "inference"}
    assert all(seconds >= 0 for seconds in correction.cpu_s.values())


def test_correct_scan__working_memory_beside_the_gate_is_one_tile(board, model, monkeypatch):
    """With the gate's whole-scan work left out, what correction holds at once shrinks with the tile."""
    from mpi_lidar.correction import gates

    big = render(cornered_board(height=240, width=320), Config(), np.random.default_rng(5), patch_spacing_m=0.1)
    potential = gates.geometry_gate(CorrectionOptions()).potential(big, big.depth[-1].ravel())
    monkeypatch.setattr(gates.GeometryGate, "potential", lambda self, scan, depth: potential)  # computed before
    peaks = {}
    for tile_pixels in (320, 10**7):
        correct_scan(big, model, CorrectionOptions(gate="all", tile_pixels=tile_pixels))  # warm caches
        tracemalloc.start()
        correct_scan(big, model, CorrectionOptions(gate="all", tile_pixels=tile_pixels))
        peaks[tile_pixels] = tracemalloc.get_traced_memory()[1]
        tracemalloc.stop()
    pixels = 240 * 320
    assert peaks[10**7] > 40 * pixels, "untiled, the raw pixels and features of the whole scan are held"
    assert peaks[320] < 20 * pixels, "tiled: the flags, depths and one tile"
