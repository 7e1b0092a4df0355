"""Pixels that face two surfaces at once: the geometry stage sums their partners' light, as the render does."""

from __future__ import annotations

import numpy as np
import pytest

from mpi_lidar.config import Config
from mpi_lidar.correction import CorrectionOptions, analyse_geometry
from mpi_lidar.scans.scan import Scan
from mpi_lidar.simulation.scenes import Scene, first_hits, light_transport, room_with_box

AREA_M2 = 0.041
CONFIG = Config()


def _multipath_free_scan(scene: Scene) -> Scan:
    """The scene's exact depth and Lambertian amplitude Gamma_R a cos_i / d^2 at every frequency (no multipath, no
    noise): the geometry the stage sees, without the render's cost."""
    d_as, which = first_hits(scene)
    h, w = scene.elevation_rad.size, scene.azimuth_rad.size
    rays = Scan("s", CONFIG.frequencies_hz, np.zeros((4, h, w), np.float32), np.ones((4, h, w), np.float32),
                azimuth_rad=scene.azimuth_rad, elevation_rad=scene.elevation_rad).rays().reshape(-1, 3)
    cos_i = np.ones(h * w)
    for index, surface in enumerate(scene.surfaces):
        on = which == index
        normals = surface.normal_at(rays[on] * d_as[on, None])
        cos_i[on] = np.abs(np.einsum("ni,ni->n", normals, rays[on]))
    albedo = np.array([s.albedo for s in scene.surfaces])[which]
    amplitude = CONFIG.sensor.gamma_r_v2 * albedo * cos_i / d_as**2
    f = len(CONFIG.frequencies_hz)
    return Scan("room", CONFIG.frequencies_hz, np.repeat(d_as.reshape(1, h, w), f, 0).astype(np.float32),
                np.repeat(amplitude.reshape(1, h, w), f, 0).astype(np.float32), azimuth_rad=scene.azimuth_rad,
                elevation_rad=scene.elevation_rad)


@pytest.mark.unit
def test_plane_model_inputs__a_pixel_facing_two_surfaces_gets_both_their_light():
    """Where a second surface sends at least a quarter of a pixel's single-bounce light, the stage's equivalent
    rho_ABA follows the render's sum over both (median within 20 %, every one within a factor 1.7) and beats the
    dominant partner alone, which would miss the second one's share. On the floor beside the box, behind the plane
    of the box's face but not behind the face, the floor's own plane must be the pixel's."""
    scene = room_with_box(bounces=2)  # the single bounces and the two bounces the stage models
    scan = _multipath_free_scan(scene)
    depth = scan.depth[-1].astype(np.float64).ravel()
    found = analyse_geometry(scan, depth, CorrectionOptions(footprint_area_m2=AREA_M2), CONFIG.sensor,
                             with_model_inputs=True)
    assert found.model_inputs is not None
    # The render's truth on a window around the tri-corner (rows 18-33, columns 24-39 of the 48 x 64 view).
    rows, columns = slice(18, 34, 3), slice(24, 40, 3)
    window = Scene("window", scene.surfaces, scene.azimuth_rad[columns], scene.elevation_rad[rows], scene.notes)
    truth: dict[str, np.ndarray] = {}
    radius = np.sqrt(AREA_M2 / (90.0 * np.pi))
    light_transport(window, CONFIG, radius, 0.03, 90.0, truth)
    grid = np.arange(depth.size).reshape(scan.shape)[rows, columns].ravel()
    estimate, _ = found.model_inputs.pixels(grid, depth[grid])
    shares = np.abs(truth["single_ratio"][:, :, 0])
    total = shares.sum(1)
    second = np.sort(shares, axis=1)[:, -2]
    two = second > 0.25 * total
    assert two.sum() >= 8
    ratio = estimate[two] / truth["rho_aba"][two]
    dominant = (shares.max(1) / total)[two]
    assert np.median(np.abs(ratio - 1)) < 0.2 and np.abs(np.log(ratio)).max() < np.log(1.7)
    assert dominant.max() < 0.8
    assert (np.abs(np.log(ratio)) < np.abs(np.log(ratio * dominant))).mean() >= 0.75


@pytest.mark.unit
def test_plane_model_inputs__the_partner_planes_bias_follows_the_render_and_two_bounces_add_to_it():
    """The bias the partner planes predict at 31.25 MHz, one path through the lowest frequency's ratio, follows the
    render's (single and two bounces) around the tri-corner within 20 % (median); without the two bounces it falls
    short where they matter."""
    scene = room_with_box(bounces=2)
    scan = _multipath_free_scan(scene)
    depth = scan.depth[-1].astype(np.float64).ravel()
    found = analyse_geometry(scan, depth, CorrectionOptions(footprint_area_m2=AREA_M2), CONFIG.sensor,
                             with_model_inputs=True)
    inputs = found.model_inputs
    assert inputs is not None and inputs.two_bounce_phasor is not None
    rows, columns = slice(18, 34, 3), slice(24, 40, 3)
    window = Scene("window", scene.surfaces, scene.azimuth_rad[columns], scene.elevation_rad[rows], scene.notes)
    truth: dict[str, np.ndarray] = {}
    light_transport(window, CONFIG, np.sqrt(AREA_M2 / (90.0 * np.pi)), 0.03, 90.0, truth)
    grid = np.arange(depth.size).reshape(scan.shape)[rows, columns].ravel()
    top = CONFIG.frequencies_hz[-1]
    true_bias = truth["bias_m"][:, -1]
    strong = true_bias > 2e-3
    assert strong.sum() >= 10
    ratio = inputs.bias_m(grid, depth[grid], top)[strong] / true_bias[strong]
    assert abs(np.median(ratio) - 1) < 0.2  # 0.90 when written
    two_bounce, inputs.two_bounce_phasor = inputs.two_bounce_phasor, None
    single_only = inputs.bias_m(grid, depth[grid], top)[strong] / true_bias[strong]
    inputs.two_bounce_phasor = two_bounce
    assert np.median(single_only) < min(0.85, np.median(ratio))  # 0.77: the two bounces' share is missing
