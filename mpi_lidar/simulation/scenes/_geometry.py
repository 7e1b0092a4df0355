"""Scene geometry: the surfaces a scene is made of, the scene and the first surface each scan ray hits.

Every surface answers the same three questions (:class:`Surface`): where a ray first meets it, its normal at a
point, and its tessellation into small patches, the patches B of the light transport.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from collections.abc import Iterator
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from mpi_lidar.scans.scan import grid_rays


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
    # Where surfaces meet [m]: concave folds (segments between two points) and tri-corners (three surfaces).
    folds: tuple[tuple[tuple[float, float, float], tuple[float, float, float]], ...] = ()
    tri_corners: tuple[tuple[float, float, float], ...] = ()


def first_hits(scene: Scene) -> tuple[NDArray, NDArray]:
    """Range d_AS (H*W,) [m] (inf for a miss) and the index of the surface hit (-1 for a miss)."""
    rays = grid_rays(scene.azimuth_rad, scene.elevation_rad).reshape(-1, 3)
    origins = np.zeros_like(rays)
    ts = np.stack([s.intersect(origins, rays) for s in scene.surfaces])
    which = np.argmin(ts, axis=0)
    t = ts[which, np.arange(rays.shape[0])]
    return t, np.where(np.isfinite(t), which, -1)


def surface_hits(scene: Scene, rays: NDArray, d_as: NDArray, which: NDArray, block_pixels: int
                 ) -> Iterator[tuple[int, Surface, NDArray, NDArray, NDArray, NDArray]]:
    """Every surface's first hits (:func:`first_hits`), ``block_pixels`` pixels at a time: the surface's index,
    the surface, the block's pixel indices, their points (n, 3) [m], the surface's unit normals there turned
    towards the scanner (n, 3), and the cosine of incidence (n,)."""
    for index, surface in enumerate(scene.surfaces):
        pixels = np.flatnonzero(which == index)
        for start in range(0, pixels.size, block_pixels):
            block = pixels[start:start + block_pixels]
            points = rays[block] * d_as[block, None]
            normals = surface.normal_at(points)
            normals = np.where((normals * rays[block]).sum(1, keepdims=True) > 0, -normals, normals)
            yield index, surface, block, points, normals, -(normals * rays[block]).sum(1)
