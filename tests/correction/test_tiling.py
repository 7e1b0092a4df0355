"""Row tiles and threads: a scan corrected tile by tile, or with its rows shared among threads, is the scan
corrected at once in one thread, to the last bit."""

from __future__ import annotations

import tracemalloc

import numpy as np
import pytest

from benchmarks.correction import finer_scan
from mpi_lidar.config import Config
from mpi_lidar.correction import CorrectionOptions, Flag, correct_scan
from mpi_lidar.correction.tiles import PARALLEL_MIN_ROWS, row_tiles
from mpi_lidar.learning.model import load_model
from mpi_lidar.reporting.correction_notes import correction_notes
from mpi_lidar.simulation.scenes import cornered_board, render
from mpi_lidar.threads import on_cores_by_rows
from tests.model_factory import tiny_model


@pytest.fixture(scope="module")
def board():
    return render(cornered_board(height=60, width=80), Config(), np.random.default_rng(4))


@pytest.fixture(scope="module", params=[True, False], ids=["geometric", "pixel-wise"])
def model(request, tmp_path_factory):
    return load_model(tiny_model(tmp_path_factory.mktemp("model") / "model", geometric=request.param))


@pytest.mark.unit
def test_row_tiles__whole_rows_cover_every_pixel_once():
    tiles = row_tiles(7, 5, 12)  # 12 pixels: two rows of 5 per tile
    assert [(t.start, t.stop) for t in tiles] == [(0, 10), (10, 20), (20, 30), (30, 35)]
    assert [(t.start, t.stop) for t in row_tiles(3, 10, 1)] == [(0, 10), (10, 20), (20, 30)]  # at least a row
    assert [(t.start, t.stop) for t in row_tiles(3, 10, 10**6)] == [(0, 30)]


@pytest.mark.integration
@pytest.mark.slow
@pytest.mark.parametrize("gate", ["geometry", "all", "consistency"])
def test_correct_scan__tiled_equals_untiled_to_the_last_bit(board, model, gate):
    whole = correct_scan(board, model, CorrectionOptions(gate=gate, tile_pixels=10**7))
    assert whole.counts()["corrected"] > 0, "the comparison must cover corrected pixels"
    # A pixel: tiles of one row (as 80 pixels would give: at least a row) and geometry tiles of one block of
    # 4 x 4 pixels each (at least a block), every boundary a tile's; several rows and a remainder, in geometry
    # bands of one block row across the width.
    for tile_pixels in (1, 7 * 80 + 13):
        tiled = correct_scan(board, model, CorrectionOptions(gate=gate, tile_pixels=tile_pixels))
        assert tiled.depth.dtype == whole.depth.dtype == np.float32
        assert tiled.depth.tobytes() == whole.depth.tobytes()
        assert tiled.flags.tobytes() == whole.flags.tobytes()
        assert tiled.estimate.tobytes() == whole.estimate.tobytes()
        assert tiled.uncertainty_m.tobytes() == whole.uncertainty_m.tobytes()
        assert (tiled.multipath_bias_m is None) == (whole.multipath_bias_m is None)
        if whole.multipath_bias_m is not None:
            assert tiled.multipath_bias_m.tobytes() == whole.multipath_bias_m.tobytes()
        assert correction_notes(tiled) == correction_notes(whole)


@pytest.mark.unit
def test_correct_scan__geometry_gate_corrects_near_the_corner_and_says_what_it_cost(board, model):
    correction = correct_scan(board, model, CorrectionOptions(tile_pixels=800, baseline="raw"))
    counts = correction.counts()
    assert counts["corrected"] > 0 and counts["no_multipath"] > 0
    gated = correction.flags == Flag.NO_MULTIPATH
    np.testing.assert_array_equal(correction.depth[gated], board.depth[-1][gated])
    assert set(correction.cpu_s) == {"unit", "validity", "gate", "inference", "baseline"}
    assert all(seconds >= 0 for seconds in correction.cpu_s.values())


@pytest.mark.unit
def test_on_cores_by_rows__ranges_cover_every_row_once_in_order(monkeypatch):
    monkeypatch.setattr("os.cpu_count", lambda: 3)
    monkeypatch.delenv("OMP_NUM_THREADS", raising=False)

    def ranges(rows: int) -> list[tuple[int, int]]:
        return on_cores_by_rows(lambda part: (part.start, part.stop), rows, PARALLEL_MIN_ROWS)

    found = ranges(3 * PARALLEL_MIN_ROWS + 1)
    assert found == [(0, PARALLEL_MIN_ROWS), (PARALLEL_MIN_ROWS, 2 * PARALLEL_MIN_ROWS),
                     (2 * PARALLEL_MIN_ROWS, 3 * PARALLEL_MIN_ROWS + 1)]
    assert ranges(2 * PARALLEL_MIN_ROWS - 1) == [(0, 2 * PARALLEL_MIN_ROWS - 1)]  # too few rows for two threads
    assert ranges(0) == [(0, 0)]


@pytest.mark.unit
def test_correct_scan__threads_share_the_rows_to_the_same_bits(board, model, monkeypatch):
    finer = finer_scan(board, 4)  # 240 x 320: one tile of 76,800 pixels, split among the threads
    assert finer.shape[0] * finer.shape[1] >= 4 * PARALLEL_MIN_ROWS
    monkeypatch.delenv("OMP_NUM_THREADS", raising=False)
    monkeypatch.setattr("os.cpu_count", lambda: 1)
    alone = correct_scan(finer, model, CorrectionOptions())
    monkeypatch.setattr("os.cpu_count", lambda: 3)
    shared = correct_scan(finer, model, CorrectionOptions())
    assert alone.model_pixels() > PARALLEL_MIN_ROWS, "the model's inputs must be built on several threads"
    assert shared.depth.tobytes() == alone.depth.tobytes()
    assert shared.flags.tobytes() == alone.flags.tobytes()
    assert shared.multipath_bias_m.tobytes() == alone.multipath_bias_m.tobytes()
    assert shared.uncertainty_m.tobytes() == alone.uncertainty_m.tobytes()
    assert shared.calibration == alone.calibration


def _peak_bytes(scans, model, options) -> list[int]:
    """The traced peak of each scan's correction, after one untraced correction of the first to warm the caches
    and lazy imports (keyed by the sensor and the frequencies, never by a scan: warming up each scan, 6 s of the
    large one's, changed nothing this test measures beyond the runs' own scatter)."""
    correct_scan(scans[0], model, options)
    peaks = []
    for scan in scans:
        tracemalloc.start()
        try:
            correct_scan(scan, model, options)
            peaks.append(tracemalloc.get_traced_memory()[1])
        finally:
            tracemalloc.stop()
    return peaks


@pytest.mark.integration
@pytest.mark.slow
@pytest.mark.parametrize("model", [True], ids=["geometric"], indirect=True)
def test_correct_scan__working_memory_grows_by_a_few_bytes_a_pixel_when_tiled(model):
    """The same scene on a grid three times as fine: tiled, the gate included, the extra pixels cost what the
    per-pixel results cost (flags, depth, measured depth, bias map, estimate, the fused depth and the sds of it
    and of the measured depth, 13 bytes of them); at once, the float64 temporaries of the whole scan.

    With the geometric model alone: a pixel-wise model's correction is the same stages less the model's geometric
    inputs (the gate's geometry is worked out for both), so it holds a subset of what is measured here, and its
    run (18 s, most of it the traced tiles) found the same growth within the runs' own scatter."""
    small = render(cornered_board(height=120, width=160), Config(), np.random.default_rng(5), patch_spacing_m=0.1)
    large = finer_scan(small, 3)
    extra = large.depth[0].size - small.depth[0].size
    growth = {}
    # Tiles of 4,800 pixels: ten rows of the large scan, thirty of the small one, so both hold bands of the same
    # size and the difference is the per-pixel cost alone (at 320 pixels, a row a tile, the traced run of the
    # tiles' own bookkeeping took most of this test's time).
    for tile_pixels in (4_800, 10**7):
        options = CorrectionOptions(tile_pixels=tile_pixels, footprint_area_m2=0.041)
        peak_small, peak_large = _peak_bytes([small, large], model, options)
        growth[tile_pixels] = (peak_large - peak_small) / extra
    assert extra > 30 * 4_800, "the extra pixels far outnumber a band's"
    assert growth[10**7] > 150, "at once, the gate's plane fits hold a few hundred bytes a pixel"
    assert growth[4_800] < 50, "tiled: the per-pixel results and one band"
