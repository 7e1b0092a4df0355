"""Scenes path traced by Mitsuba 3 (benchmarks/mitsuba_render.py) against closed forms and the project's renderer."""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest

from benchmarks.mitsuba_render import PROFILE_DISTANCES_M, path_trace, scan_of, true_bias_m
from mpi_lidar.config import Config
from mpi_lidar.physics.coupling import DEFAULT_COUPLING_GAIN
from mpi_lidar.scans.scan import grid_rays
from mpi_lidar.simulation.scenes import Rectangle, corner, first_hits, flat_wall, light_transport, room_with_box

pytestmark = pytest.mark.integration
CONFIG = Config()


def _phase_depth_m(phasor: np.ndarray) -> np.ndarray:
    """The depth [m] of the highest frequency's phasor (F, H, W), unwrapped into the first period."""
    f, c = CONFIG.frequencies_hz[-1], CONFIG.sensor.speed_of_light_m_per_s
    return np.mod(np.angle(phasor[-1]), 2 * np.pi) * c / (4 * np.pi * f)


def test_a_plane_returns_the_closed_form_amplitude_and_its_range():
    # One plane: no path but the direct one, whose amplitude is Gamma_R rho cos_i / d^2 (F3) and phase 2 d.
    scene = flat_wall(tilt_deg=30.0, distance_m=2.0, albedo=0.6, height=3, width=5)
    traced = path_trace(scene, CONFIG, 0.04, samples=256)
    ranges, _ = first_hits(scene)
    rays = grid_rays(scene.azimuth_rad, scene.elevation_rad).reshape(-1, 3)
    wall = scene.surfaces[0]
    assert isinstance(wall, Rectangle)
    normal = np.cross(wall.half_u, wall.half_v)
    cos_i = np.abs(rays @ normal) / np.linalg.norm(normal)
    expected = CONFIG.sensor.gamma_r_v2 * 0.6 * cos_i / ranges**2
    np.testing.assert_allclose(np.abs(traced.direct[-1]).ravel(), expected, rtol=2e-3)
    np.testing.assert_allclose(traced.phasor, traced.direct, rtol=1e-5)
    np.testing.assert_allclose(_phase_depth_m(traced.direct).ravel(), ranges, atol=5e-5)


def test_a_corner_carries_the_multipath_the_project_renderer_predicts_beyond_the_beam():
    # Beyond the beam's reach of the fold the light is what the project's kernel (F4) integrates over the facing
    # board, plus the higher bounces the single-bounce corner leaves out (some 5-10 %); nearer, the beam lights the
    # facing board directly, which the kernel only caps.
    area, scene = 0.04, corner(90.0, 2.0, 0.8, 3, 32)
    traced = path_trace(scene, CONFIG, area, samples=16384)
    truth: dict[str, np.ndarray] = {}
    light_transport(scene, CONFIG, float(np.sqrt(area / (DEFAULT_COUPLING_GAIN * np.pi))), 0.01,
                    DEFAULT_COUPLING_GAIN, truth)
    ranges, _ = first_hits(scene)
    points = ranges[:, None] * grid_rays(scene.azimuth_rad, scene.elevation_rad).reshape(-1, 3)
    away = (np.abs(points[:, 0]) > np.sqrt(area / np.pi)) & np.isfinite(ranges)
    project = truth["bias_m"][:, -1][away]
    path_traced = true_bias_m(traced, CONFIG).ravel()[away]
    assert away.sum() >= 30 and project.max() > 3e-3, "pixels with millimetres of multipath"
    # Monte Carlo noise of 16,384 paths: about 0.3 mm of bias per pixel.
    assert np.abs(path_traced - project).max() < 1e-3
    assert path_traced.mean() / project.mean() == pytest.approx(1.05, abs=0.06)


def test_a_path_traced_scan_reads_its_range_through_the_sensor_model():
    scene = flat_wall(distance_m=2.0, height=4, width=6)
    traced = path_trace(scene, CONFIG, 0.04, samples=64)
    scan = scan_of(scene, traced, CONFIG, np.random.default_rng(0))
    assert scan.reference_depth is not None
    error = scan.depth[-1] - scan.reference_depth
    assert np.abs(error).max() < 0.01 and abs(float(error.mean())) < 2e-3  # Table I noise: about 1 mm per pixel
    assert scan.name.endswith("(path traced)")


def test_bias_profile_command__a_row_per_distance_and_more_bias_with_more_bounces():
    # 24 pixels across (each path traced four times): every distance from 3 cm on still gets its own pixel
    # within 1 cm of it, as at the default 96.
    done = subprocess.run([sys.executable, "-m", "benchmarks.mitsuba_render", "--angle", "90", "--samples", "64",
                           "--columns", "24"], capture_output=True, text=True, check=True, timeout=300)
    rows = [line.strip("|").split("|") for line in done.stdout.splitlines() if line.startswith("| 0.")]
    assert [float(cells[0]) for cells in rows] == list(PROFILE_DISTANCES_M)
    for cells in rows[2:]:  # from 3 cm on: right at the fold the multi-bounce renderer's occlusion takes some away
        single, three = float(cells[1]), float(cells[2])
        assert three >= single > 0, cells  # the higher bounces add light along longer paths in a concave corner


def test_a_rooms_one_sided_faces_return_their_closed_form_towards_the_scanner():
    # The room's faces reflect on their inner side only (as the project's renderer has them): a face handed to
    # Mitsuba the wrong way round would return nothing.
    scene = room_with_box(height=6, width=8)
    traced = path_trace(scene, CONFIG, 0.002, samples=64)
    ranges, which = first_hits(scene)
    rays = grid_rays(scene.azimuth_rad, scene.elevation_rad).reshape(-1, 3)
    expected = []
    for ray, distance, surface in zip(rays, ranges, which, strict=True):
        face = scene.surfaces[surface]
        assert isinstance(face, Rectangle) and not face.two_sided
        normal = np.cross(face.half_u, face.half_v)
        expected.append(CONFIG.sensor.gamma_r_v2 * face.albedo * abs(ray @ normal) / np.linalg.norm(normal)
                        / distance**2)
    amplitude = np.abs(traced.direct[-1]).ravel()
    inside = amplitude > 0.9 * np.asarray(expected)  # a pixel whose ray grazes a face's border returns part
    assert inside.mean() > 0.9
    np.testing.assert_allclose(amplitude[inside], np.asarray(expected)[inside], rtol=2e-3)
