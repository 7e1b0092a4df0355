"""The scene-geometry stage (mpi_lidar.correction.scene) and the gates as policies over its result."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from mpi_lidar.config import Config
from mpi_lidar.correction import (
    NO_GEOMETRY_INPUTS_NOTE,
    NO_GEOMETRY_NOTE,
    CorrectionOptions,
    GateName,
    SceneGeometry,
    analyse_geometry,
    make_gate,
)
from mpi_lidar.correction.gates import ConsistencyGate, CorrectAll, GeometryGate
from mpi_lidar.correction.scene import depth_sigma_map
from mpi_lidar.physics.noise import NoiseModel
from mpi_lidar.simulation.scenes import corner, render

pytestmark = pytest.mark.unit


@pytest.fixture(scope="module")
def corner_scan():
    return render(corner(90.0, 2.0, 0.8, height=32, width=64), Config(), np.random.default_rng(2))


def usable_depth(scan) -> np.ndarray:
    return np.where(np.isfinite(scan.depth[-1]), scan.depth[-1], np.nan).ravel().astype(np.float32)


@pytest.fixture(scope="module")
def scene(corner_scan) -> SceneGeometry:
    return analyse_geometry(corner_scan, usable_depth(corner_scan), CorrectionOptions(footprint_area_m2=0.041),
                            Config().sensor, with_model_inputs=True)


def test_analyse_geometry__given_footprint_gives_bias_map_candidates_and_inputs(scene, corner_scan):
    assert scene.has_geometry and scene.footprint is None and scene.footprint_m2 == 0.041
    assert scene.bias_m is not None and scene.bias_m.dtype == np.float32 and scene.bias_m.shape == corner_scan.shape
    threshold = CorrectionOptions().min_multipath_bias_m
    np.testing.assert_array_equal(scene.reaches_min_bias, (np.abs(scene.bias_m) >= threshold).ravel())
    assert scene.reaches_min_bias.any() and not scene.reaches_min_bias.all()
    assert scene.model_inputs is not None and scene.uncalibrated is None and scene.notes == ()


def test_scene_geometry__is_frozen(scene):
    with pytest.raises(dataclasses.FrozenInstanceError):
        scene.footprint_m2 = 1.0  # type: ignore[misc]


def test_gates__are_pure_functions_of_the_scene(scene):
    options = CorrectionOptions()
    for gate in (make_gate(options), make_gate(options)):
        assert gate == GeometryGate() and gate.candidates(scene) is scene.reaches_min_bias
    assert GeometryGate().candidates(None) is None
    assert CorrectAll().candidates(scene) is None and ConsistencyGate(0.01).candidates(scene) is None
    assert make_gate(CorrectionOptions(gate="consistency", consistency_p_value=0.05)) == ConsistencyGate(0.05)
    assert {make_gate(CorrectionOptions(gate=name)).name for name in GateName} == set(GateName)


def test_analyse_geometry__without_rays_only_says_so(corner_scan):
    scan = dataclasses.replace(corner_scan, azimuth_rad=None, elevation_rad=None)
    depth = usable_depth(scan)
    geometry = analyse_geometry(scan, depth, CorrectionOptions(), Config().sensor)
    assert not geometry.has_geometry and geometry.notes == (NO_GEOMETRY_NOTE,) and geometry.bias_m is None
    assert analyse_geometry(scan, depth, CorrectionOptions(), Config().sensor,
                            with_model_inputs=True).notes == (NO_GEOMETRY_INPUTS_NOTE,)
    assert analyse_geometry(scan, depth, CorrectionOptions(gate="all"), Config().sensor).notes == ()


@pytest.mark.parametrize("noise_scale", [1.0, 1.7])
def test_depth_sigma_map__is_the_highest_frequencys_sd_of_the_noise_law(corner_scan, noise_scale):
    noise = NoiseModel.for_sensor(Config().sensor, corner_scan.frequencies_hz, noise_scale)
    depth = usable_depth(corner_scan)
    depth[::7] = np.nan
    sigma = depth_sigma_map(corner_scan, depth, noise, tile_pixels=500)
    amplitude = np.asarray(corner_scan.amplitude, dtype=np.float64).reshape(len(corner_scan.frequencies_hz), -1).T
    expected = np.where(np.isfinite(depth), noise.depth_sigma_m(amplitude)[:, -1], np.nan).astype(np.float32)
    np.testing.assert_array_equal(sigma.ravel(), expected)
