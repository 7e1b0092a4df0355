"""Scene simulator: scans of simple geometric scenes through the coaxial scanning geometry.

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

from abc import ABC, abstractmethod
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import TYPE_CHECKING, Unpack

import numpy as np
from numpy.typing import NDArray

from mpi_lidar.config import Config
from mpi_lidar.physics import demod, make_sensor
from mpi_lidar.physics.coupling import (
    DEFAULT_COUPLING_GAIN,
    DEFAULT_FOOTPRINT_RADIUS_M,
    footprint_area,
    footprint_coupling,
    pair_geometry,
)
from mpi_lidar.physics.sensor import received_voltage_amplitude
from mpi_lidar.physics.transport import path_phasor
from mpi_lidar.scans.scan import Scan, grid_rays
from mpi_lidar.scans.store import write_scan

if TYPE_CHECKING:
    from mpi_lidar.scans.scan import ScanExtras

DEFAULT_PATCH_SPACING_M = 0.02
PIXEL_BLOCK = 512


class Surface(ABC):
    """A scene surface.

    Contract: ``intersect(origins, directions)`` returns the ray parameter t (N,) of the first hit in front
    of each ray, inf for a miss; ``normal_at(points)`` returns unit normals (N, 3) (outward for solids; for
    a planar surface either side, the caller orients it); ``patches(spacing)`` tessellates the surface into
    (centres (M, 3), normals (M, 3), areas (M,)); ``albedo`` is its Lambertian reflectance; ``planar`` says
    whether it is a flat surface, shown in the reference mask; ``two_sided`` whether light leaves both its
    faces (a thin board) or only the one its normal points to (the outside of a solid).
    """

    albedo: float
    planar: bool
    two_sided: bool

    @abstractmethod
    def intersect(self, origins: NDArray, directions: NDArray) -> NDArray[np.float64]: ...

    @abstractmethod
    def normal_at(self, points: NDArray) -> NDArray[np.float64]: ...

    @abstractmethod
    def patches(self, spacing_m: float) -> tuple[NDArray, NDArray, NDArray]: ...


@dataclass(frozen=True)
class Rectangle(Surface):
    """A planar rectangle: centre [m] and two orthogonal half-extent vectors [m].

    A board by default, seen and lit from either side. A face of a solid is ``two_sided=False``: its normal,
    half_u x half_v, points out of the solid, and no light leaves its inner side (the renderer does not trace
    occlusion, so an inner side would light what lies beyond the solid through it).
    """

    centre: tuple[float, float, float]
    half_u: tuple[float, float, float]
    half_v: tuple[float, float, float]
    albedo: float = 0.8
    planar: bool = True
    two_sided: bool = True

    def _frame(self) -> tuple[NDArray, NDArray, NDArray, NDArray]:
        c, u, v = (np.asarray(x, dtype=np.float64) for x in (self.centre, self.half_u, self.half_v))
        n = np.cross(u, v)
        return c, u, v, n / np.linalg.norm(n)

    def intersect(self, origins: NDArray, directions: NDArray) -> NDArray[np.float64]:
        c, u, v, n = self._frame()
        denom = directions @ n
        with np.errstate(divide="ignore", invalid="ignore"):  # rays parallel to the plane: no hit
            t = ((c - origins) @ n) / denom
            hit = origins + t[:, None] * directions
        rel = hit - c
        inside = (np.abs(rel @ u) <= u @ u) & (np.abs(rel @ v) <= v @ v)
        return np.where(inside & (t > 1e-9) & (np.abs(denom) > 1e-12), t, np.inf)

    def normal_at(self, points: NDArray) -> NDArray[np.float64]:
        return np.broadcast_to(self._frame()[3], np.shape(points)).copy()

    def patches(self, spacing_m: float) -> tuple[NDArray, NDArray, NDArray]:
        c, u, v, n = self._frame()
        nu = max(1, round(2 * np.linalg.norm(u) / spacing_m))
        nv = max(1, round(2 * np.linalg.norm(v) / spacing_m))
        su, sv = (np.arange(nu) + 0.5) / nu * 2 - 1, (np.arange(nv) + 0.5) / nv * 2 - 1
        grid_u, grid_v = np.meshgrid(su, sv, indexing="ij")
        centres = c + grid_u.reshape(-1, 1) * u + grid_v.reshape(-1, 1) * v
        area = 4 * np.linalg.norm(u) * np.linalg.norm(v) / (nu * nv)
        return centres, np.broadcast_to(n, centres.shape).copy(), np.full(len(centres), area)


@dataclass(frozen=True)
class Sphere(Surface):
    """A sphere: centre [m], radius [m]. Convex: only its outside counts."""

    centre: tuple[float, float, float]
    radius: float
    albedo: float = 0.6
    planar: bool = False
    two_sided: bool = False

    def intersect(self, origins: NDArray, directions: NDArray) -> NDArray[np.float64]:
        oc = origins - np.asarray(self.centre)
        b = np.einsum("ij,ij->i", oc, directions)
        disc = b**2 - (np.einsum("ij,ij->i", oc, oc) - self.radius**2)
        root = np.sqrt(np.maximum(disc, 0.0))
        t = np.where(-b - root > 1e-9, -b - root, -b + root)
        return np.where((disc >= 0) & (t > 1e-9), t, np.inf)

    def normal_at(self, points: NDArray) -> NDArray[np.float64]:
        n = points - np.asarray(self.centre)
        return n / np.linalg.norm(n, axis=-1, keepdims=True)

    def patches(self, spacing_m: float) -> tuple[NDArray, NDArray, NDArray]:
        count = max(8, round(4 * np.pi * self.radius**2 / spacing_m**2))
        k = np.arange(count) + 0.5  # Fibonacci sphere: near-equal areas
        polar = np.arccos(1 - 2 * k / count)
        azimuth = np.pi * (1 + 5**0.5) * k
        normals = np.column_stack([np.sin(polar) * np.cos(azimuth), np.cos(polar), np.sin(polar) * np.sin(azimuth)])
        centres = np.asarray(self.centre) + self.radius * normals
        return centres, normals, np.full(count, 4 * np.pi * self.radius**2 / count)


@dataclass(frozen=True)
class Cylinder(Surface):
    """A vertical cylinder (axis along y): base centre [m], radius [m], height [m]; its side only."""

    base: tuple[float, float, float]
    radius: float
    height: float
    albedo: float = 0.6
    planar: bool = False
    two_sided: bool = False

    def intersect(self, origins: NDArray, directions: NDArray) -> NDArray[np.float64]:
        base = np.asarray(self.base)
        o, d = (origins - base)[:, [0, 2]], directions[:, [0, 2]]
        a = np.einsum("ij,ij->i", d, d)
        b = np.einsum("ij,ij->i", o, d)
        disc = b**2 - a * (np.einsum("ij,ij->i", o, o) - self.radius**2)
        root = np.sqrt(np.maximum(disc, 0.0))
        with np.errstate(divide="ignore", invalid="ignore"):
            t = np.where((-b - root) / a > 1e-9, (-b - root) / a, (-b + root) / a)
        y = origins[:, 1] + t * directions[:, 1] - base[1]
        ok = (disc >= 0) & (a > 1e-12) & (t > 1e-9) & (y >= 0) & (y <= self.height)
        return np.where(ok, t, np.inf)

    def normal_at(self, points: NDArray) -> NDArray[np.float64]:
        n = points - np.asarray(self.base)
        n[:, 1] = 0.0
        return n / np.linalg.norm(n, axis=-1, keepdims=True)

    def patches(self, spacing_m: float) -> tuple[NDArray, NDArray, NDArray]:
        around = max(8, round(2 * np.pi * self.radius / spacing_m))
        up = max(1, round(self.height / spacing_m))
        angle = (np.arange(around) + 0.5) * 2 * np.pi / around
        y = (np.arange(up) + 0.5) * self.height / up
        a, h = np.meshgrid(angle, y, indexing="ij")
        normals = np.column_stack([np.sin(a.ravel()), np.zeros(a.size), np.cos(a.ravel())])
        centres = np.asarray(self.base) + self.radius * normals + np.outer(h.ravel(), [0.0, 1.0, 0.0])
        return centres, normals, np.full(a.size, 2 * np.pi * self.radius * self.height / (around * up))


def prism(base: tuple[float, float, float], radius: float, height: float, sides: int = 6,
          albedo: float = 0.45, rotation_rad: float = 0.0) -> list[Rectangle]:
    """A vertical regular prism (a hexagonal pillar by default) as one-sided rectangles facing outwards."""
    faces = []
    for k in range(sides):
        a0, a1 = rotation_rad + 2 * np.pi * k / sides, rotation_rad + 2 * np.pi * (k + 1) / sides
        p0 = np.array([np.sin(a0), 0.0, np.cos(a0)]) * radius
        p1 = np.array([np.sin(a1), 0.0, np.cos(a1)]) * radius
        centre = np.asarray(base) + (p0 + p1) / 2 + [0.0, height / 2, 0.0]
        half_u = (p1 - p0) / 2
        faces.append(Rectangle(tuple(centre), tuple(half_u), (0.0, height / 2, 0.0), albedo, two_sided=False))
    return faces


@dataclass(frozen=True)
class Scene:
    """Surfaces and the scan grid that looks at them. Curved surfaces are left out of the reference mask."""

    name: str
    surfaces: tuple[Surface, ...]
    azimuth_rad: NDArray[np.float64]
    elevation_rad: NDArray[np.float64]
    notes: dict[str, float] = field(default_factory=dict)  # e.g. angle_deg, patch_spacing_m; copied to the scan


def _grid(height: int, width: int, half_width_rad: float, half_height_rad: float,
          centre_az_rad: float = 0.0) -> tuple[NDArray, NDArray]:
    azimuth = centre_az_rad + np.linspace(-half_width_rad, half_width_rad, width)
    elevation = np.linspace(half_height_rad, -half_height_rad, height)  # row 0 is the top
    return azimuth, elevation


def first_hits(scene: Scene) -> tuple[NDArray, NDArray]:
    """Range d_AS (H*W,) [m] (inf for a miss) and the index of the surface hit (-1 for a miss)."""
    rays = grid_rays(scene.azimuth_rad, scene.elevation_rad).reshape(-1, 3)
    origins = np.zeros_like(rays)
    ts = np.stack([s.intersect(origins, rays) for s in scene.surfaces])
    which = np.argmin(ts, axis=0)
    t = ts[which, np.arange(rays.shape[0])]
    return t, np.where(np.isfinite(t), which, -1)


def render(scene: Scene, config: Config, rng: np.random.Generator, *,
           footprint_radius_m: float = DEFAULT_FOOTPRINT_RADIUS_M,
           patch_spacing_m: float | None = None, coupling_gain: float = DEFAULT_COUPLING_GAIN,
           truth_out: dict[str, NDArray] | None = None) -> Scan:
    """Render a scan: exact reference depth, two-path-per-patch light transport, then the sensor model.

    ``patch_spacing_m`` defaults to the scene's own (large scenes use coarser patches) or 2 cm. A dict passed
    as ``truth_out`` receives the render's true multipath per pixel (:func:`light_transport`'s
    ``coupling_out``).
    """
    patch_spacing_m = patch_spacing_m or float(scene.notes.get("patch_spacing_m", DEFAULT_PATCH_SPACING_M))
    phasor, dc = light_transport(scene, config, footprint_radius_m, patch_spacing_m, coupling_gain, truth_out)
    depth, amplitude = sense(phasor, dc, config, rng)
    h, w = scene.elevation_rad.size, scene.azimuth_rad.size
    d_as, which = first_hits(scene)
    reference = np.where(np.isfinite(d_as), d_as, np.nan).reshape(h, w)
    return Scan(
        name=scene.name, frequencies_hz=config.frequencies_hz,
        depth=depth.reshape(-1, h, w).astype(np.float32), amplitude=amplitude.reshape(-1, h, w).astype(np.float32),
        azimuth_rad=scene.azimuth_rad, elevation_rad=scene.elevation_rad,
        reference_depth=reference.astype(np.float32), reference_mask=simple_region_mask(scene, which.reshape(h, w)),
        scene={"scene": scene.name, "surfaces": len(scene.surfaces), "footprint_radius_m": footprint_radius_m,
               "coupling_gain": coupling_gain, **scene.notes, "patch_spacing_m": patch_spacing_m},
    )


def simple_region_mask(scene: Scene, which: NDArray) -> NDArray[np.bool_]:
    """Pixels on a planar surface whose 3 x 3 neighbourhood hits the same surface (no depth edge)."""
    planar = np.array([s.planar for s in scene.surfaces] + [False])  # index -1: a miss
    padded = np.pad(which, 1, mode="edge")
    same = np.ones_like(which, dtype=bool)
    for dy in (-1, 0, 1):
        for dx in (-1, 0, 1):
            same &= padded[1 + dy:padded.shape[0] - 1 + dy, 1 + dx:padded.shape[1] - 1 + dx] == which
    return same & planar[which] & (which >= 0)


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
    """
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
    for index, surface in enumerate(scene.surfaces):
        pixels = np.flatnonzero(which == index)
        for start in range(0, pixels.size, PIXEL_BLOCK):
            block = pixels[start:start + PIXEL_BLOCK]
            points = rays[block] * d_as[block, None]
            normals = surface.normal_at(points)
            normals = np.where((normals * rays[block]).sum(1, keepdims=True) > 0, -normals, normals)
            cos_i = -(normals * rays[block]).sum(1)
            gamma_d = s.gamma_r_v2 * surface.albedo * cos_i / d_as[block] ** 2  # eq 12
            multipath = np.zeros((block.size, freqs.size), dtype=np.complex128)
            multipath_dc = np.zeros(block.size)
            kappa = np.zeros(block.size)
            ratio_r = np.zeros(block.size)
            for other, (centres, patch_normals, areas) in enumerate(patches):
                if other == index:
                    continue  # planar and convex surfaces do not see themselves
                ratio, r = _patch_coupling(points, normals, cos_i, surface.albedo, scene.surfaces[other],
                                           centres, patch_normals, areas, effective_footprint, patch_spacing_m)
                wave = path_phasor(1.0, r[:, :, None], freqs[None, None, :], c)  # eq 15: d_AS + r
                multipath += np.einsum("nm,nmf->nf", ratio, wave)  # eq 13, 15: one term per patch
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


def _patch_coupling(points, normals, cos_i, albedo_a, other: Surface, centres, patch_normals, areas,
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


def sense(phasor: NDArray, dc: NDArray, config: Config, rng: np.random.Generator) -> tuple[NDArray, NDArray]:
    """Depth (F, N) [m] and amplitude (F, N) [V^2] of correlation phasors (N, F) through the sensor model."""
    s = config.sensor
    to_volts = received_voltage_amplitude(1.0, s.modulation_contrast, s.demodulation_amplitude_v)
    taps = make_sensor(config).taps_from_phasors(dc * to_volts, phasor * to_volts, rng)
    depth, amplitude = demod.depth_and_amplitude(taps, config.frequencies_hz, s.speed_of_light_m_per_s)
    return depth.T, amplitude.T


# --- named scenes -------------------------------------------------------------------------------------------


def cornered_board(height: int = 120, width: int = 160, albedo: float = 0.8) -> Scene:
    """Fig. 7: two white boards forming a concave 90-degree corner with a vertical edge, 2.05-2.25 m away,
    seen 12 degrees off its bisector, so the right board is hit more obliquely and returns less light."""
    edge = np.array([0.0, 0.0, 2.25])
    yaw = np.deg2rad(12)
    left = np.array([-np.cos(np.pi / 4 + yaw), 0.0, -np.sin(np.pi / 4 + yaw)])  # from the edge along each board
    right = np.array([np.cos(np.pi / 4 - yaw), 0.0, -np.sin(np.pi / 4 - yaw)])
    up = np.array([0.0, 0.35, 0.0])
    boards = (_board(edge, left, 0.45, up, albedo), _board(edge, right, 0.45, up, albedo))
    return Scene("cornered_board", boards, *_grid(height, width, 0.14, 0.105))


def _board(edge: NDArray, along: NDArray, length: float, up: NDArray, albedo: float) -> Rectangle:
    """A board running ``length`` from ``edge`` along ``along`` and ``up`` (its half extent) either side."""
    centre = edge + along * length / 2
    return Rectangle(tuple(centre), tuple(along * length / 2), tuple(up), albedo)


def corner(angle_deg: float = 90.0, distance_m: float = 2.0, albedo: float = 0.8, height: int = 96,
           width: int = 128, *, board_m: float = 0.5, half_height_m: float = 0.35, yaw_deg: float = 0.0,
           roll_deg: float = 0.0, albedo_right: float | None = None) -> Scene:
    """A concave corner of two boards meeting at ``angle_deg`` with its edge ``distance_m`` away, facing us.

    The boards run ``board_m`` from the edge and ``half_height_m`` either side of the view's axis along it
    (the defaults reach beyond the view from 1.4 m on). ``yaw_deg`` turns the corner about its edge, so the
    view is off its bisector; ``roll_deg`` turns the whole corner about the view's axis (90: a horizontal
    edge, as where a wall meets the floor). ``albedo_right`` gives the right board its own albedo.
    """
    half, yaw, roll = np.deg2rad(angle_deg) / 2, np.deg2rad(yaw_deg), np.deg2rad(roll_deg)
    turn = np.array([[np.cos(roll), -np.sin(roll), 0.0], [np.sin(roll), np.cos(roll), 0.0], [0.0, 0.0, 1.0]])
    edge = np.array([0.0, 0.0, distance_m])
    left = turn @ np.array([-np.sin(half + yaw), 0.0, -np.cos(half + yaw)])
    right = turn @ np.array([np.sin(half - yaw), 0.0, -np.cos(half - yaw)])
    up = turn @ np.array([0.0, half_height_m, 0.0])
    boards = (_board(edge, left, board_m, up, albedo),
              _board(edge, right, board_m, up, albedo if albedo_right is None else albedo_right))
    return Scene(f"corner_{angle_deg:g}deg_{distance_m:g}m_a{albedo:g}", boards,
                 *_grid(height, width, 0.12, 0.09), notes={"angle_deg": angle_deg})


def wooden_corner(height: int = 96, width: int = 128) -> Scene:
    """Fig. 10: a 90-degree corner of wooden plates (albedo 0.45) beyond 2 m."""
    scene = corner(90.0, 2.3, 0.45, height, width)
    return Scene("wooden_corner", scene.surfaces, scene.azimuth_rad, scene.elevation_rad)


def flat_wall(tilt_deg: float = 0.0, distance_m: float = 2.0, albedo: float = 0.7, height: int = 96,
              width: int = 128) -> Scene:
    """A single plane (no multipath possible), turned by ``tilt_deg`` about the vertical axis."""
    tilt = np.deg2rad(tilt_deg)
    wall = Rectangle((0.0, 0.0, distance_m), (2.0 * np.cos(tilt), 0.0, 2.0 * np.sin(tilt)), (0.0, 1.5, 0.0), albedo)
    return Scene(f"flat_wall_{tilt_deg:g}deg" if tilt_deg else "flat_wall", (wall,), *_grid(height, width, 0.2, 0.15))


def multi_object(height: int = 120, width: int = 160) -> Scene:
    """Fig. 8: a wooden corner structure (back and side walls, floor; 1.65-2.4 m, inside the paper's d_AS
    range), a hexagonal pillar next to the back wall, and a sphere standing in for the curved bust. The sphere
    is left out of the reference mask."""
    wood = 0.45
    back = Rectangle((0.1, 0.0, 2.35), (0.8, 0.0, 0.0), (0.0, 0.5, 0.0), wood)
    side = Rectangle((-0.7, 0.0, 2.0), (0.0, 0.0, 0.35), (0.0, 0.5, 0.0), wood)
    floor = Rectangle((0.1, -0.5, 2.0), (0.8, 0.0, 0.0), (0.0, 0.0, 0.35), wood)
    pillar = prism((0.35, -0.5, 2.2), 0.08, 0.8, albedo=0.55)
    bust = Sphere((-0.3, -0.3, 2.05), 0.16, albedo=0.7)
    return Scene("multi_object", (back, side, floor, *pillar, bust), *_grid(height, width, 0.2, 0.15),
                 notes={"patch_spacing_m": 0.04})


def cylinder_scene(height: int = 96, width: int = 128) -> Scene:
    """A convex cylinder with open sky around it: no surface can send light back to it."""
    return Scene("cylinder", (Cylinder((0.0, -0.4, 2.0), 0.2, 0.8, 0.7),), *_grid(height, width, 0.15, 0.12))


def sphere_scene(height: int = 96, width: int = 128) -> Scene:
    """A convex sphere with open sky around it."""
    return Scene("sphere", (Sphere((0.0, 0.0, 2.0), 0.25, 0.7),), *_grid(height, width, 0.15, 0.12))


def room_corner(albedo: float = 0.7, height: int = 96, width: int = 128) -> Scene:
    """Where two walls meet the floor: a back wall 2.2 m away, a side wall 0.3 m to the left of the view's axis
    and a floor 0.2 m below it, so three surfaces face each other along three edges."""
    back = Rectangle((0.2, 0.3, 2.2), (0.5, 0.0, 0.0), (0.0, 0.5, 0.0), albedo)
    side = Rectangle((-0.3, 0.3, 1.7), (0.0, 0.0, 0.5), (0.0, 0.5, 0.0), albedo)
    floor = Rectangle((0.2, -0.2, 1.7), (0.5, 0.0, 0.0), (0.0, 0.0, 0.5), albedo)
    return Scene("room_corner", (back, side, floor), *_grid(height, width, 0.2, 0.15))


def alcove(albedo: float = 0.5, height: int = 96, width: int = 128) -> Scene:
    """A recess 0.6 m wide and 0.6 m deep, its back 2.3 m away: two parallel side walls face each other and
    both face the back."""
    back = Rectangle((0.0, 0.0, 2.3), (0.3, 0.0, 0.0), (0.0, 0.4, 0.0), albedo)
    left = Rectangle((-0.3, 0.0, 2.0), (0.0, 0.0, 0.3), (0.0, 0.4, 0.0), albedo)
    right = Rectangle((0.3, 0.0, 2.0), (0.0, 0.0, 0.3), (0.0, 0.4, 0.0), albedo)
    return Scene("alcove", (back, left, right), *_grid(height, width, 0.2, 0.15))


def box_on_floor(floor_albedo: float = 0.4, box_albedo: float = 0.8, pitch_deg: float = 27.0, height: int = 96,
                 width: int = 128) -> Scene:
    """A box 0.5 m wide and deep and 0.4 m high on the floor, 2 m ahead of a sensor 1 m above the floor that
    looks down by ``pitch_deg``: the sensor sees the box's front and top, and its sides and back, hidden from
    the sensor, light the floor beside and behind it. The box's faces send light from their outsides only."""
    floor = Rectangle((0.0, -1.0, 2.2), (1.2, 0.0, 0.0), (0.0, 0.0, 1.2), floor_albedo)
    up, half_width = (0.0, 0.2, 0.0), 0.25  # half the box's height, half its width and depth [m]
    front = Rectangle((0.0, -0.8, 2.0), (-half_width, 0.0, 0.0), up, box_albedo, two_sided=False)
    back = Rectangle((0.0, -0.8, 2.5), (half_width, 0.0, 0.0), up, box_albedo, two_sided=False)
    top = Rectangle((0.0, -0.6, 2.25), (half_width, 0.0, 0.0), (0.0, 0.0, -half_width), box_albedo, two_sided=False)
    sides = tuple(Rectangle((x, -0.8, 2.25), (0.0, 0.0, -np.sign(x) * half_width), up, box_albedo, two_sided=False)
                  for x in (-half_width, half_width))
    return Scene("box_on_floor", _pitched((floor, front, back, top, *sides), pitch_deg),
                 *_grid(height, width, 0.25, 0.19))


def floor_meets_wall(floor_albedo: float = 0.6, wall_albedo: float = 0.7, pitch_deg: float = 20.0, height: int = 96,
                     width: int = 128) -> Scene:
    """A wall 2.6 m ahead of a sensor 1 m above the floor that looks down by ``pitch_deg``: the floor meets the
    wall along a horizontal edge."""
    floor = Rectangle((0.0, -1.0, 2.0), (1.2, 0.0, 0.0), (0.0, 0.0, 0.6), floor_albedo)
    wall = Rectangle((0.0, -0.2, 2.6), (1.2, 0.0, 0.0), (0.0, 0.8, 0.0), wall_albedo)
    return Scene("floor_meets_wall", _pitched((floor, wall), pitch_deg), *_grid(height, width, 0.2, 0.15))


def pitch_rotation(pitch_deg: float) -> NDArray[np.float64]:
    """The rotation that brings the world into the frame of a sensor looking down by ``pitch_deg``."""
    a = np.deg2rad(pitch_deg)
    return np.array([[1.0, 0.0, 0.0], [0.0, np.cos(a), np.sin(a)], [0.0, -np.sin(a), np.cos(a)]])


def _pitched(rectangles: tuple[Rectangle, ...], pitch_deg: float) -> tuple[Rectangle, ...]:
    """Rectangles as a sensor looking down by ``pitch_deg`` sees them (the view's axis stays z)."""
    turn = pitch_rotation(pitch_deg)
    return tuple(replace(r, centre=tuple(turn @ np.asarray(r.centre)), half_u=tuple(turn @ np.asarray(r.half_u)),
                         half_v=tuple(turn @ np.asarray(r.half_v))) for r in rectangles)


SCENES: dict[str, Callable[..., Scene]] = {
    "cornered_board": cornered_board, "multi_object": multi_object, "wooden_corner": wooden_corner,
    "flat_wall": flat_wall, "corner": corner, "cylinder": cylinder_scene, "sphere": sphere_scene,
    "room_corner": room_corner, "alcove": alcove, "box_on_floor": box_on_floor, "floor_meets_wall": floor_meets_wall,
}
DEMO_SCENES = ("cornered_board", "multi_object", "flat_wall")


def render_scenes(out_dir: str | Path, names: tuple[str, ...] = DEMO_SCENES, config: Config | None = None,
                  seed: int = 0) -> list[Path]:
    """Render named scenes into ``<out_dir>/<name>.scan.zarr``, each seeded by (seed, its position in SCENES)."""
    config = config or Config()
    order = list(SCENES)
    paths = []
    for name in names:
        rng = np.random.default_rng(np.random.SeedSequence(seed, spawn_key=(order.index(name),)))
        scan = render(SCENES[name](), config, rng)
        paths.append(write_scan(scan, Path(out_dir) / f"{name}.scan.zarr", overwrite=True))
    return paths


# --- external renders -------------------------------------------------------------------------------------


def scan_from_phasors(name: str, gamma_phasor: NDArray, config: Config, rng: np.random.Generator,
                      dc_gamma: NDArray | None = None, **optional: Unpack[ScanExtras]) -> Scan:
    """A scan from externally rendered correlation phasors (F, H, W) [V^2] (eq 11) through our sensor model.

    ``dc_gamma`` (F, H, W) is the sum of the path magnitudes [V^2]; without it the magnitude of the phasor
    is used, which is exact for one path per pixel and a lower bound otherwise.
    """
    phasor = np.asarray(gamma_phasor, dtype=np.complex128)
    f, h, w = phasor.shape
    dc = np.abs(phasor) if dc_gamma is None else np.asarray(dc_gamma, dtype=np.float64)
    depth, amplitude = sense(phasor.reshape(f, -1).T, dc.reshape(f, -1).T, config, rng)
    return Scan(name=name, frequencies_hz=config.frequencies_hz, depth=depth.reshape(f, h, w).astype(np.float32),
                amplitude=amplitude.reshape(f, h, w).astype(np.float32), **optional)


def scan_from_transient(name: str, histogram: NDArray, bin_s: float, config: Config, rng: np.random.Generator,
                        **optional: Unpack[ScanExtras]) -> Scan:
    """A scan from transient histograms (T, H, W): correlation amplitude [V^2] per round-trip-time bin [s].

    The phasor at f is sum_t h(t) e^{j 2 pi f t} (t the bin's round-trip time) and the DC part sum_t h(t).
    """
    h = np.asarray(histogram, dtype=np.float64)
    times = np.arange(h.shape[0]) * bin_s
    # e^{+j 2 pi f t} with t = 2 d / c: the phasor convention of mpi_lidar.physics.transport
    kernel = np.exp(2j * np.pi * np.outer(config.frequencies_hz, times))  # (F, T)
    phasor = np.tensordot(kernel, h, axes=(1, 0))  # (F, H, W)
    dc = np.broadcast_to(h.sum(0), phasor.shape)
    return scan_from_phasors(name, phasor, config, rng, dc_gamma=dc, **optional)
