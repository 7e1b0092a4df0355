"""The per-pixel estimate: the model's depth where the gate hands it pixels, the fused baseline elsewhere, and
every depth's uncertainty, in one pass over the tiles."""

from __future__ import annotations

import numpy as np
import pytest

from mpi_lidar.config import SensorConfig
from mpi_lidar.correction.baseline import FrequencyOffsets
from mpi_lidar.correction.estimates import ScenePart, estimate_pixels
from mpi_lidar.correction.gates import CorrectAll
from mpi_lidar.correction.gating import decide
from mpi_lidar.correction.options import CorrectionOptions, Estimate, Flag
from mpi_lidar.correction.tiles import StageClock, scan_tiles
from mpi_lidar.correction.validity import check_validity
from mpi_lidar.learning.model import load_model
from mpi_lidar.physics.noise import NoiseModel
from tests.model_factory import tiny_model
from tests.scan_factory import two_path_scan

pytestmark = pytest.mark.unit


@pytest.fixture(scope="module")
def pixel_wise_model(tmp_path_factory):
    return load_model(tiny_model(tmp_path_factory.mktemp("estimates") / "model", geometric=False, rounds=10))


def _estimate(model, d_as_m, options, tile_pixels=50):
    scan = two_path_scan("estimates", height=8, width=12)
    noise = NoiseModel.for_sensor(SensorConfig(), scan.frequencies_hz)
    tiles = scan_tiles(scan, tile_pixels)
    validity = check_validity(scan, noise, options, tiles)
    decision = decide(validity, CorrectAll(), None, d_as_m, options, geometric_model=False)
    pixels = estimate_pixels(validity.scan, tiles, noise, decision.flags, validity, ScenePart(), model,
                             FrequencyOffsets(), options, StageClock())
    return scan, decision, pixels


def test_estimate_pixels__corrected_pixels_take_the_models_depth_the_others_the_fused_one(pixel_wise_model):
    options = CorrectionOptions(amplitude_scale=1.0)
    scan, decision, pixels = _estimate(pixel_wise_model, (1.4, 2.4), options)
    corrected = decision.flags == Flag.CORRECTED
    assert corrected.all(), "every pixel of the wall is valid and in range"
    raw = scan.raw_pixels()
    np.testing.assert_array_equal(pixels.depth, pixel_wise_model.predict_depth(raw).astype(np.float32))
    assert (pixels.estimate == Estimate.CORRECTED).all() and np.isfinite(pixels.uncertainty_m).all()
    _, far, fused = _estimate(pixel_wise_model, (5.0, 8.0), options)
    assert (far.flags == Flag.OUT_OF_RANGE).all() and fused.inference_s == 0.0
    noise = NoiseModel.for_sensor(SensorConfig(), scan.frequencies_hz)
    expected = noise.fuse(raw)
    consistent = expected.consistent
    np.testing.assert_array_equal(fused.depth[consistent], expected.depth_m[consistent])
    np.testing.assert_array_equal(fused.uncertainty_m[consistent], expected.sigma_m[consistent])
    assert (fused.estimate[consistent] == Estimate.FUSED).all()
    assert (fused.depth[~consistent] == raw[~consistent, 3]).all(), "disagreeing frequencies: as measured"


def test_estimate_pixels__the_tiles_do_not_change_a_bit(pixel_wise_model):
    options = CorrectionOptions(amplitude_scale=1.0)
    whole = _estimate(pixel_wise_model, (1.4, 2.4), options, tile_pixels=10_000)[2]
    tiled = _estimate(pixel_wise_model, (1.4, 2.4), options, tile_pixels=12)[2]
    for name in ("depth", "estimate", "uncertainty_m"):
        assert getattr(whole, name).tobytes() == getattr(tiled, name).tobytes(), name
