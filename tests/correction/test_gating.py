"""The gate stage: the gate's policy, the scan's own footprint, the model's range and a pixel-wise gate's decision."""

from __future__ import annotations

import numpy as np
import pytest

from mpi_lidar.config import SensorConfig
from mpi_lidar.correction.gates import ConsistencyGate, CorrectAll, GeometryGate
from mpi_lidar.correction.gating import decide, in_depth_range
from mpi_lidar.correction.options import CorrectionOptions, Flag
from mpi_lidar.correction.scene import SceneGeometry
from mpi_lidar.correction.tiles import scan_tiles
from mpi_lidar.correction.validity import check_validity
from mpi_lidar.physics.noise import NoiseModel
from tests.scan_factory import two_path_scan

pytestmark = pytest.mark.unit

OPTIONS = CorrectionOptions(amplitude_scale=1.0)


def _validity(gate=None, **scan_options):
    scan = two_path_scan("gated", height=6, width=10, **scan_options)
    noise = NoiseModel.for_sensor(SensorConfig(), scan.frequencies_hz)
    return check_validity(scan, noise, OPTIONS, scan_tiles(scan, 1000), gate)


def test_in_depth_range__the_near_end_moves_in_by_its_fraction_and_both_widen_by_the_tolerance():
    options = CorrectionOptions(near_range_fraction=0.2, range_tolerance_m=0.1)
    depth = np.array([0.69, 0.71, 2.0, 3.09, 3.11])
    np.testing.assert_array_equal(in_depth_range(depth, (1.0, 3.0), options), [False, True, True, True, False])


def test_decide__every_valid_pixel_in_range_is_corrected_by_the_pixel_wise_model():
    validity = _validity()
    decision = decide(validity, CorrectAll(), None, (1.4, 2.4), OPTIONS, geometric_model=False)
    valid = validity.flags == Flag.NOT_NEEDED
    assert decision.served and valid.any()
    assert (decision.flags[valid] == Flag.CORRECTED).all()
    assert np.array_equal(decision.flags[~valid], validity.flags[~valid]), "invalid pixels keep their reason"
    assert (validity.flags[valid] == Flag.NOT_NEEDED).all(), "the validity stage's flags are not edited"


def test_decide__outside_the_models_range_is_out_of_range_and_a_geometric_model_without_geometry_serves_none():
    validity = _validity()
    far = decide(validity, CorrectAll(), None, (5.0, 8.0), OPTIONS, geometric_model=False)
    assert (far.flags[validity.flags == Flag.NOT_NEEDED] == Flag.OUT_OF_RANGE).all()
    blind = decide(validity, CorrectAll(), None, (1.4, 2.4), OPTIONS, geometric_model=True)
    assert not blind.served and not (blind.flags == Flag.CORRECTED).any()


def test_decide__the_geometry_gate_rules_out_what_its_scene_does_not_reach_and_counts_the_uncalibrated():
    validity = _validity()
    size = validity.flags.size
    reaches = np.zeros(size, bool)
    reaches[: size // 2] = True
    uncalibrated = np.zeros(size, bool)
    uncalibrated[:3] = True
    scene = SceneGeometry(reaches_min_bias=reaches, uncalibrated=uncalibrated)
    decision = decide(validity, GeometryGate(), scene, (1.4, 2.4), OPTIONS, geometric_model=False)
    valid = validity.flags == Flag.NOT_NEEDED
    assert decision.uncalibrated_pixels == int((valid & uncalibrated).sum()) > 0
    assert (decision.flags[valid & ~reaches] == Flag.NO_MULTIPATH).all()
    assert (decision.flags[valid & reaches & ~uncalibrated] == Flag.CORRECTED).all()


def test_decide__a_pixel_wise_gate_corrects_only_what_it_asked_for_in_the_validity_pass():
    validity = _validity(ConsistencyGate(0.01))
    assert validity.needs_correction is not None
    decision = decide(validity, ConsistencyGate(0.01), None, (1.4, 2.4), OPTIONS, geometric_model=False)
    corrected = decision.flags == Flag.CORRECTED
    np.testing.assert_array_equal(corrected, (validity.flags == Flag.NOT_NEEDED) & validity.needs_correction)
