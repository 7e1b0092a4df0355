"""Light transport: the direct path and the two-path multipath of every scan direction of a scene.

For each scan direction the first surface hit is A. The direct path (eq 12, 14) returns from A with
Gamma_D = Gamma_R a cos_i / d_AS^2 for a Lambertian surface of albedo a hit at incidence cos_i. The
multipath A -> B -> A (eq 13, 15) is integrated over small patches B of the other surfaces; each patch adds

    Gamma_M,B = Gamma_D a b kappa_B,   kappa_B = (cos_A cos_B)^2 dA_B A_fp / (pi^2 r^4 cos_i),
    phase 4 pi f (d_AS + r) / c,

the kernel of :mod:`mpi_lidar.physics.coupling` (its derivation, and the calibration of the effective
footprint A_fp = ``coupling_gain`` pi r_fp^2 to the paper's Fig. 7, are given there). Summed over B this is
the paper's reciprocal prior with coupling kappa (ratio Gamma_M / Gamma_D = a kappa b). Only patches facing
A (cos_A, cos_B > 0) count; r is clamped below by the patch spacing (the finite beam smooths the 1/r^4
singularity at a corner line); occlusion between A and B is ignored, which is exact for the corners and
walls here and approximate for the multi-object scene. A planar or convex surface never sees itself. The
summed coupling is capped at kappa = 1 (A cannot get back more than all its light through B), which binds
only next to a corner line.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from mpi_lidar.config import Config
from mpi_lidar.physics.coupling import footprint_area, footprint_coupling, pair_geometry
from mpi_lidar.physics.transport import path_phasor, phasor_sums
from mpi_lidar.scans.scan import grid_rays
from mpi_lidar.simulation.scenes._geometry import Scene, Surface, first_hits, surface_hits
from mpi_lidar.simulation.scenes._multibounce import multibounce_transport

PIXEL_BLOCK = 512


def light_transport(scene: Scene, config: Config, footprint_radius_m: float, patch_spacing_m: float,
                    coupling_gain: float = 1.0, coupling_out: dict[str, NDArray] | None = None,
                    ) -> tuple[NDArray[np.complex128], NDArray[np.float64]]:
    """Per pixel and frequency: the complex correlation phasor (H*W, F) [V^2] and the DC sum of amplitudes.

    Returns (phasor, dc) where dc is sum |Gamma_k| over paths [V^2]. A dict passed as ``coupling_out``
    receives the true per-pixel multipath of the render: ``coupling`` (H*W,), the summed kappa of the
    prior (ratio Gamma_M / Gamma_D over a b, after the cap at 1; the quantity
    :func:`mpi_lidar.scans.geometry.multipath_potential` estimates) [1], ``rho_aba`` (H*W,), the ratio over
    the albedo a cos_i the pixel's amplitude shows (the rho_ABA of the surface facing the sensor with the same
    multipath, which :meth:`mpi_lidar.scans.geometry.FacingBlocks.equivalent_rho_aba` estimates) [1],
    ``d_ab_m`` (H*W,), the ratio-weighted mean A-B distance [m] (NaN without multipath), and ``bias_m``
    (H*W, F), the depth bias the multipath alone gives each frequency, without noise [m] (NaN where no surface
    is hit).

    A scene whose notes name its ``bounces`` is rendered with up to that many bounces and with occlusion
    (:func:`._multibounce.multibounce_transport`), which gives ``coupling_out`` more.
    """
    if "bounces" in scene.notes:
        return multibounce_transport(scene, config, footprint_radius_m, patch_spacing_m, coupling_gain, coupling_out,
                                     bounces=int(scene.notes["bounces"]))
    s = config.sensor
    c = s.speed_of_light_m_per_s
    freqs = np.asarray(config.frequencies_hz)
    rays = grid_rays(scene.azimuth_rad, scene.elevation_rad).reshape(-1, 3)
    d_as, which = first_hits(scene)
    phasor = np.zeros((rays.shape[0], freqs.size), dtype=np.complex128)
    dc = np.zeros((rays.shape[0], freqs.size))
    patches = [s_.patches(patch_spacing_m) for s_ in scene.surfaces]
    true_kappa = np.zeros(rays.shape[0])
    true_rho_aba = np.zeros(rays.shape[0])
    true_d_ab = np.full(rays.shape[0], np.nan)
    true_bias = np.full((rays.shape[0], freqs.size), np.nan)
    effective_footprint = footprint_area(footprint_radius_m, coupling_gain)
    for index, surface, block, points, normals, cos_i in surface_hits(scene, rays, d_as, which, PIXEL_BLOCK):
        gamma_d = s.gamma_r_v2 * surface.albedo * cos_i / d_as[block] ** 2  # eq 12
        multipath = np.zeros((block.size, freqs.size), dtype=np.complex128)
        multipath_dc = np.zeros(block.size)
        kappa = np.zeros(block.size)
        ratio_r = np.zeros(block.size)
        for other, (centres, patch_normals, areas) in enumerate(patches):
            if other == index:
                continue  # planar and convex surfaces do not see themselves
            ratio, r = patch_coupling(points, normals, cos_i, surface.albedo, scene.surfaces[other],
                                       centres, patch_normals, areas, effective_footprint, patch_spacing_m)
            multipath += phasor_sums(ratio, r, freqs, c)  # eq 13, 15: one term per patch at d_AS + r
            multipath_dc += ratio.sum(1)
            kappa += ratio.sum(1) / (surface.albedo * scene.surfaces[other].albedo)
            ratio_r += (ratio * r).sum(1)
        # Energy: A cannot get back more than all its light through B (kappa <= 1, as in the prior).
        scale = 1.0 / np.maximum(kappa, 1.0)
        true_kappa[block] = kappa * scale
        true_rho_aba[block] = scale * multipath_dc / (surface.albedo * cos_i)
        with np.errstate(invalid="ignore", divide="ignore"):
            true_d_ab[block] = np.where(multipath_dc > 0, ratio_r / multipath_dc, np.nan)
        direct = path_phasor(gamma_d[:, None], d_as[block, None], freqs[None, :], c)  # eq 12, 14
        both_paths = 1 + scale[:, None] * multipath  # per unit of the direct path
        true_bias[block] = np.angle(both_paths) * c / (4 * np.pi * freqs)
        phasor[block] = direct * both_paths
        dc[block] = gamma_d[:, None] * (1 + scale * multipath_dc)[:, None]
    if coupling_out is not None:
        coupling_out.update(coupling=true_kappa, rho_aba=true_rho_aba, d_ab_m=true_d_ab, bias_m=true_bias)
    return phasor, dc


def patch_coupling(points, normals, cos_i, albedo_a, other: Surface, centres, patch_normals, areas,
                    footprint_area: float, min_r: float) -> tuple[NDArray, NDArray]:
    """Gamma_M,B / Gamma_D (n, M) and the A-B distance (n, M) [m] for every patch of another surface.

    The kernel is :func:`mpi_lidar.physics.coupling.footprint_coupling`; here pairs face each other when both
    cosines are positive, r is clamped below by ``min_r`` (the patch spacing) and cos_i by 1e-3.
    """
    r, cos_a, cos_b = pair_geometry(points[:, None, :], normals[:, None, :], centres[None, :, :],
                                    patch_normals[None, :, :])
    if other.two_sided:
        cos_b = np.abs(cos_b)  # either side of a board faces A if A is in front of it
    facing = (cos_a > 0) & (cos_b > 0)
    ratio = footprint_coupling(cos_a, cos_b, areas[None, :], np.maximum(r, min_r), np.maximum(cos_i, 1e-3)[:, None],
                               footprint_area, reflectance=albedo_a * other.albedo)
    return np.where(facing, ratio, 0.0), r
