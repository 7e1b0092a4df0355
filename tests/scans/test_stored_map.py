"""A large scan stays in its store: read a band of rows at a time, it corrects exactly as it does in memory."""

from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import zarr

from benchmarks.correction import finer_scan
from mpi_lidar.config import Config
from mpi_lidar.correction import CorrectionOptions, correct_scan
from mpi_lidar.learning.model import load_model
from mpi_lidar.reporting.correction_notes import correction_notes
from mpi_lidar.reporting.metrics import scan_metrics
from mpi_lidar.scans.scan import ScanError
from mpi_lidar.scans.store import SCAN_SCHEMA, read_scan, store_fingerprints, write_scan
from mpi_lidar.scans.stored_map import StoredMap
from mpi_lidar.simulation.scenes import cornered_board, render
from mpi_lidar.storage.integrity import IntegrityError
from mpi_lidar.workflows import correct_archive
from tests.model_factory import tiny_model
from tests.scan_factory import two_path_scan
from tests.storage.test_integrity import DAMAGES, damage


@pytest.fixture(scope="module")
def tall_store(tmp_path_factory) -> Path:
    """A rendered corner 600 rows tall: two chunk rows of 512, so tiles straddle a chunk boundary."""
    board = render(cornered_board(height=150, width=40), Config(), np.random.default_rng(8), patch_spacing_m=0.1)
    return write_scan(finer_scan(board, 4), tmp_path_factory.mktemp("tall") / "tall.scan.zarr")


@pytest.fixture(scope="module")
def model_dir(tmp_path_factory) -> Path:
    return tiny_model(tmp_path_factory.mktemp("model") / "model", geometric=True)


@pytest.fixture(scope="module")
def model(model_dir):
    return load_model(model_dir)


@pytest.mark.unit
def test_stored_map__slices_pixels_and_bytes_are_those_of_the_array(tall_store):
    memory, stored = read_scan(tall_store), read_scan(tall_store, stored_above_bytes=0)
    assert isinstance(stored.depth, StoredMap) and isinstance(stored.amplitude, StoredMap)
    assert not isinstance(memory.depth, StoredMap)
    assert stored.depth.shape == memory.depth.shape and stored.shape == memory.shape
    np.testing.assert_array_equal(np.asarray(stored.depth), memory.depth)
    for key in ((slice(None), slice(500, 530)), (-1, slice(0, 600), slice(3, 9)), (2,), (slice(None), slice(590, 700))):
        np.testing.assert_array_equal(stored.depth[key], memory.depth[key])
    ys, xs = np.array([0, 511, 512, 599, 3]), np.array([0, 159, 7, 80, 3])
    np.testing.assert_array_equal(stored.amplitude[:, ys, xs], memory.amplitude[:, ys, xs])
    assert stored.content_sha256() == memory.content_sha256()


@pytest.mark.unit
def test_stored_map__ray_directions_stay_in_the_store_and_give_the_same_rays(tmp_path):
    scan = two_path_scan("rays", 30, 20)
    scan = replace(scan, ray_directions=scan.rays().astype(np.float32), azimuth_rad=None, elevation_rad=None)
    stored = read_scan(write_scan(scan, tmp_path / "rays.scan.zarr"), stored_above_bytes=0)
    assert isinstance(stored.ray_directions, StoredMap)
    np.testing.assert_array_equal(stored.ray_rows()[4:9], scan.ray_rows()[4:9])
    ys, xs = np.array([0, 29, 5]), np.array([19, 0, 5])
    np.testing.assert_array_equal(stored.pixel_rays(ys, xs), scan.pixel_rays(ys, xs))
    assert stored.content_sha256() == scan.content_sha256()


def tiled(footprint: float | str) -> CorrectionOptions:
    """Tiles of 21 rows and a remainder: one of them (rows 504-525) straddles the store's chunk boundary at row
    512, and most end inside a row of blocks. Blocks of 10 cm, 26 x 26 pixels here, about 6 x 6 of the coarse
    render's own pixels (each repeated 4 x 4 times): smaller ones hold too few independent depths for their planes
    to stand out of the noise; the geometry's tiles take 4 of them and a remainder across the width."""
    return CorrectionOptions(footprint_area_m2=footprint, tile_pixels=21 * 160 + 13, geometry_block_m=0.1)


@pytest.fixture(scope="module")
def in_memory(tall_store, model):
    """The tall scan read into memory and its correction with :func:`tiled` options, once per footprint."""
    corrections = {}

    def corrected(footprint: float | str):
        if footprint not in corrections:
            scan = read_scan(tall_store)
            corrections[footprint] = scan, correct_scan(scan, model, tiled(footprint))
        return corrections[footprint]

    return corrected


@pytest.mark.integration
@pytest.mark.slow
@pytest.mark.parametrize("footprint", ["auto", 0.041])
def test_correct_scan__stored_maps_correct_to_the_last_bit_as_in_memory(tall_store, model, in_memory, footprint):
    stored = read_scan(tall_store, stored_above_bytes=0)
    memory, expected = in_memory(footprint)
    found = correct_scan(stored, model, tiled(footprint))
    counts = expected.counts()
    assert counts["corrected"] + counts["uncalibrated"] > 0, "the gate's decisions must be part of the comparison"
    assert found.depth.tobytes() == expected.depth.tobytes() and found.flags.tobytes() == expected.flags.tobytes()
    assert found.multipath_bias_m.tobytes() == expected.multipath_bias_m.tobytes()
    assert correction_notes(found) == correction_notes(expected)
    assert scan_metrics(stored, found) == scan_metrics(memory, expected)


@pytest.mark.integration
def test_scan_metrics__banded_sums_match_the_whole_map_within_rounding(in_memory):
    scan, correction = in_memory(0.041)  # tiled: the same bits as at once (tests/correction/test_tiling.py)
    metrics = scan_metrics(scan, correction)["whole map"]
    where = np.isfinite(scan.reference_depth) & np.isfinite(correction.depth)
    error = correction.depth[where].astype(np.float64) - scan.reference_depth[where]
    assert metrics["pixels"] == where.sum()
    assert metrics["corrected_mae_m"] == pytest.approx(np.abs(error).mean(), rel=1e-12)
    assert metrics["corrected_rmse_m"] == pytest.approx(np.sqrt((error**2).mean()), rel=1e-12)
    assert metrics["corrected_max_abs_m"] == np.abs(error).max()


@pytest.mark.unit
@pytest.mark.parametrize("how", DAMAGES)
def test_read_scan__damaged_chunk_of_a_stored_map_is_refused_when_opened(tmp_path, how):
    path = write_scan(two_path_scan("d", 24, 32), tmp_path / "d.scan.zarr")
    spare = write_scan(two_path_scan("e", 24, 32, seed=3), tmp_path / "e.scan.zarr")
    if how == "swapped":  # the same chunk of another scan: it decodes, but holds other values
        (path / "amplitude" / "c" / "1" / "0" / "0").write_bytes((spare / "amplitude" / "c" / "1" / "0" / "0")
                                                                 .read_bytes())
    else:
        damage(path, "amplitude", "1/0/0", "0/0/0", how)
    with pytest.raises(IntegrityError, match="amplitude"):
        read_scan(path, stored_above_bytes=0)


@pytest.mark.unit
def test_read_scan__stored_maps_are_validated_like_arrays_in_memory(tmp_path):
    scan = two_path_scan("bad", 12, 16)
    group = zarr.open_group(str(tmp_path / "bad.scan.zarr"), mode="w")
    amplitude = scan.amplitude.copy()
    amplitude[1, 2, 3] = -1.0
    group.create_array("depth", data=scan.depth)
    group.create_array("amplitude", data=amplitude)
    group.attrs.update({"schema": SCAN_SCHEMA, "frequencies_hz": list(scan.frequencies_hz),
                        "chunk_sha256": store_fingerprints(group)})
    for threshold in (float("inf"), 0):
        with pytest.raises(ScanError, match=r"amplitude has negative values \(1 pixels\)"):
            read_scan(tmp_path / "bad.scan.zarr", stored_above_bytes=threshold)


@pytest.mark.integration
@pytest.mark.slow
def test_process_scan__a_scan_above_the_threshold_is_read_from_its_store_with_the_same_outputs(
        tall_store, model_dir, tmp_path, monkeypatch):
    options = CorrectionOptions(footprint_area_m2=0.041, geometry_block_m=0.1)  # as :func:`tiled`'s blocks
    in_memory = correct_archive.process_scan(tall_store, model_dir, tmp_path / "memory", options, outputs="data")
    opened = []
    monkeypatch.setattr(correct_archive, "STORED_MAPS_ABOVE_BYTES", 0)
    monkeypatch.setattr(correct_archive, "read_scan", lambda *a, **k: opened.append(k) or read_scan(*a, **k))
    stored = correct_archive.process_scan(tall_store, model_dir, tmp_path / "stored", options, outputs="data")
    assert opened == [{"stored_above_bytes": 0}]
    assert in_memory.status == stored.status == "corrected" and in_memory.counts == stored.counts
    assert in_memory.metrics == stored.metrics
    for name in ("corrected_depth", "flags", "multipath_bias_m"):
        a = zarr.open_group(str(Path(in_memory.output) / "corrected.zarr"), mode="r")[name][...]
        b = zarr.open_group(str(Path(stored.output) / "corrected.zarr"), mode="r")[name][...]
        assert a.tobytes() == b.tobytes()
    metrics = [json.loads((Path(o.output) / "metrics.json").read_text()) for o in (in_memory, stored)]
    assert metrics[0]["counts"] == metrics[1]["counts"]
