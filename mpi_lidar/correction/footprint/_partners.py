"""The multipath partners of the fit: the scan's flat surfaces as planes, continued beyond the view.

The footprint fit compares the depth a scan measured with the bias its geometry predicts. The scan's own 3 cm
blocks describe that geometry poorly where it matters most:

- Near a shared edge the multipath bends the measured surface (by centimetres at strong coupling), so the
  blocks there sit and tilt where the surface is not, and the coupling worked out from them is off by a
  factor of up to two within a few centimetres of the edge.
- A wall or board rarely ends where the field of view does. Its parts beyond the view send light back like
  the parts within it, and in a narrow view they give much of the bias far from the edge.
- A block across an edge holds pixels of both surfaces; on the wrong surface's plane a pixel reads the
  distance between the two as multipath.

:class:`PlanePartners` therefore models every flat surface (:func:`._surfaces.surface_labels`) by its plane
(:class:`SurfacePlane`), tiled with square patches (:class:`Patches`): where the scan sees that surface or
something behind it, and beyond the view where the scan's border shows the surface running on (or a surface it
meets, in front of which it runs on: a floor below the wall seen at the border), out to :data:`REACH` times its
visible size from its visible centre, and nowhere behind the plane of a surface that bounds it (a wall its
floor). The patches are :data:`PATCH_M` wide next to the other surfaces and grow with the distance from them.
Each patch B of area dA_B couples to a point A as

(F4)  kappa_B = (cos_A cos_B)^2 dA_B / (pi^2 max(r, sqrt(dA_B))^4 cos_i)   at A_fp = 1 m^2,

the renderer's kernel (:func:`mpi_lidar.physics.coupling.footprint_coupling`). A receiving point lies on its own
surface's plane; each pixel belongs to the surface, among its block's and the neighbouring blocks', whose plane
lies nearest its measured range. Partners that are not flat surfaces (curved ones) keep their block pairs
(:class:`BlockPairs`); a strip of blocks along an edge, the bend itself, is no partner.
"""


from __future__ import annotations

import functools
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import NDArray

from mpi_lidar.correction.footprint._facing_pairs import (
    block_pairs_off_planes,
    meeting_surfaces,
    surfaces_facing,
)
from mpi_lidar.correction.footprint._plane_coupling import coupling_at, dot3
from mpi_lidar.scans.geometry import FacingBlocks
from mpi_lidar.scans.scan import Scan

if TYPE_CHECKING:
    from scipy.spatial import cKDTree

# A continued surface reaches this many times as far from its visible centre as its farthest visible block.
REACH = 2.0
# Surfaces (connected blocks) narrower than this many blocks across are neither modelled as planes nor
# partners: a strip along an edge is the bend of the multipath.
MIN_SPAN_BLOCKS = 3
# Patch side next to a receiving surface [m], growing by one such side every GRADING_M further from it: the
# coupling falls as 1 / r^4, so far patches may be coarse.
PATCH_M = 0.02
GRADING_M = 0.05
# The patches of the two-bounce light (:mod:`._two_bounce`), which changes slowly across a surface: five times as
# wide next to a receiving surface, growing every TWO_BOUNCE_GRADING_M (the multi-bounce renderer's choice).
TWO_BOUNCE_PATCH_M = 0.10
TWO_BOUNCE_GRADING_M = 0.15
# Within the view a patch counts where it lies no nearer than this [m] in front of what the scan measured
# there (the multipath moves the measured surface by centimetres near an edge).
FRONT_TOLERANCE_M = 0.05
# A block whose normal lies more than 66 degrees from its ray (the cosine below this) is seen at a grazing angle:
# its range runs across it at tan(66 deg) = 2.2 times its width or more, and a ray's own range on its plane stands.
GRAZING_COSINE = 0.4
# A surface's plane hides what lies behind it up to this many times its visible size from its visible centre.
HIDING_REACH = 1.25


@dataclass(frozen=True)
class SurfacePlane:
    """A flat surface's plane.

    Attributes
    ----------
    normal : NDArray[np.float64]
        Unit normal (3,), towards the scanner.
    centre : NDArray[np.float64]
        The visible part's centre (3,) on the plane. [m]
    visible_m : float
        Distance of the farthest visible block from ``centre``. [m]
    """

    normal: NDArray[np.float64]
    centre: NDArray[np.float64]
    visible_m: float

    @property
    def vector(self) -> NDArray[np.float64]:
        """The plane as u . x = 1 (u (3,) [1/m]), the form the footprint fit's planes take."""
        return self.normal / (self.normal @ self.centre)


@dataclass(frozen=True)
class Patches:
    """Square patches tiling a plane: centres (m, 3) [m] and areas (m,) [m^2]."""

    centres: NDArray[np.float64]
    areas_m2: NDArray[np.float64]


class PlanePartners:
    """The flat surfaces of a scan as planes with their patches, and the curved partners' block pairs.

    :meth:`at_points` gives the white unit-footprint coupling of points from every modelled plane, each point
    on its own surface's plane. The planes run through the surfaces' block centres; ``fitted`` planes
    (u . x = 1 [1/m], by surface label) take the place of those it names. The block pairs the planes do not
    describe are :attr:`curved` (receivers on a plane, partners on none) and :attr:`off_plane` (receivers on
    none).
    """

    def __init__(self, scan: Scan, blocks: FacingBlocks, components: NDArray, labels: NDArray,
                 fitted: dict[int, NDArray] | None = None):
        narrow = _narrow_components(blocks, components)
        self.block_rays = _block_rays(scan, blocks)
        self.planes = _surface_planes(blocks, labels, narrow)
        for surface, plane in (fitted or {}).items():
            if surface in self.planes:
                self.planes[surface] = _moved_plane(self.planes[surface], plane)
        self.blocks, self.components = blocks, components
        self.patches = _surface_patches(blocks, components, self.planes, self.block_rays)
        self.partners = sorted(self.patches)
        # A block of each plane's surface, whose albedo stands for the plane's.
        self.partner_block = np.array([np.flatnonzero(components == p)[0] for p in self.partners], dtype=np.intp)
        self.curved, self.off_plane = block_pairs_off_planes(blocks, components, labels, narrow, set(self.planes),
                                                             set(self.patches))
        # The planes each surface receives light from: those its blocks have facing pairs with.
        self.facing = surfaces_facing(blocks, labels, components, set(self.planes), set(self.patches))

    @functools.cached_property
    def coarse_patches(self) -> dict[int, Patches]:
        """The patched planes' coarser patches (:data:`TWO_BOUNCE_PATCH_M`, :data:`TWO_BOUNCE_GRADING_M`), by surface
        label: those of the two-bounce light."""
        coarse = _surface_patches(self.blocks, self.components, self.planes, self.block_rays, TWO_BOUNCE_PATCH_M,
                                  TWO_BOUNCE_GRADING_M)
        return {surface: patches for surface, patches in coarse.items() if surface in self.patches}

    def at_points(self, rays: NDArray, surface: NDArray, frequencies_hz: tuple[float, ...],
                  speed_of_light_m_per_s: float) -> tuple[NDArray[np.complex128], NDArray[np.float64]]:
        """Per point (n,) and partner plane: sum kappa_B e^{j 4 pi f r / c} (n, P, F) and sum kappa_B (n, P)
        at A_fp = 1 m^2 (F4), for points where the rays (n, 3) meet the planes of their surfaces ``surface`` (n,)
        (zero for a point on no plane)."""
        n, planes = rays.shape[0], len(self.partners)
        phasor = np.zeros((n, planes, len(frequencies_hz)), dtype=np.complex128)
        kappa = np.zeros((n, planes))
        for own in np.unique(surface):
            if int(own) not in self.planes:
                continue
            rows = np.flatnonzero(surface == own)
            own_plane = self.planes[int(own)]
            points = on_plane(rays[rows], own_plane)
            for column, partner in enumerate(self.partners):
                if partner not in self.facing[int(own)]:
                    continue
                partner_plane, patches = self.planes[partner], self.patches[partner]
                # Only patches in front of the receiving plane and points in front of the partner's face.
                ahead = (patches.centres - own_plane.centre) @ own_plane.normal > 0
                lit = dot3(points - partner_plane.centre, partner_plane.normal) > 0
                if not ahead.any() or not lit.any():
                    continue
                values = coupling_at(points[lit], own_plane.normal, patches.centres[ahead],
                                      patches.areas_m2[ahead], partner_plane.normal, frequencies_hz,
                                      speed_of_light_m_per_s)
                kappa[rows[lit], column] = values[:, 0].real
                phasor[rows[lit], column] = values[:, 1:]
        return phasor, kappa

    def nearest_surface(self, rays: NDArray, range_m: NDArray, block_rows: NDArray, block_columns: NDArray,
                        labels: NDArray) -> NDArray[np.intp]:
        """Each point's flat surface: of the surfaces (``labels``, (Hb, Wb)) of its block and the eight around
        it, and the surfaces facing those, the one whose plane lies nearest the range it measured; its block's
        label where none is a plane.

        A surface whose plane the ray meets behind the plane of a surface facing it is no candidate: past
        their shared edge the other surface is the one seen. Next to an edge the two planes lie within the
        noise of each other, and a pixel given the wrong one there has no coupling, so it would join the
        anchors and tilt its plane (on a 120-degree corner without multipath by 0.7 mm at the edge, read as
        a footprint of several 10^-3 m^2). The facing surfaces are candidates because strong multipath bends
        a surface's blocks next to its edge away from it (they are left out of every surface): the block a
        pixel lies in may then belong to the other surface alone, whose plane it lies behind."""
        surface = labels[block_rows, block_columns].copy()
        planes = sorted(self.planes)
        candidate = self._candidate_planes(planes, block_rows, block_columns, labels)
        gap = np.full(surface.shape, np.inf)
        for column, plane_surface in enumerate(planes):
            rows = np.flatnonzero(candidate[:, column])
            points = on_plane(rays[rows], self.planes[plane_surface])
            with np.errstate(invalid="ignore"):
                distance = np.abs(np.linalg.norm(points, axis=1) - range_m[rows])
                distance[self._behind_a_partner(points, plane_surface)] = np.inf
                nearer = distance < gap[rows]
            surface[rows[nearer]], gap[rows[nearer]] = plane_surface, distance[nearer]
        return surface

    def _candidate_planes(self, planes: list[int], block_rows: NDArray, block_columns: NDArray, labels: NDArray
                          ) -> NDArray[np.bool_]:
        """Per point (n,) and plane of ``planes`` (P,): whether the plane's surface is that of the point's block
        or one of the eight around it, or faces one of those."""
        hb, wb = labels.shape
        column_of = {plane_surface: column for column, plane_surface in enumerate(planes)}
        around_point = np.zeros((block_rows.size, len(planes)), dtype=bool)
        for dy in (-1, 0, 1):
            for dx in (-1, 0, 1):
                around = labels[np.clip(block_rows + dy, 0, hb - 1), np.clip(block_columns + dx, 0, wb - 1)]
                for label in np.unique(around):
                    if int(label) in column_of:
                        around_point[:, column_of[int(label)]] |= around == label
        candidate = around_point.copy()
        for column, plane_surface in enumerate(planes):
            for partner in self.facing[plane_surface]:  # patched surfaces, all of them planes
                candidate[:, column_of[partner]] |= around_point[:, column]
        return candidate

    def _behind_a_partner(self, points: NDArray, surface: int) -> NDArray[np.bool_]:
        """Points (n,) on ``surface``'s plane that lie behind the plane of a surface facing it, where the ray to
        the point meets that plane within :data:`HIDING_REACH` times the partner's visible size from its centre.

        A partner is a surface of finite size: a box's face on a floor hides the floor behind it, not the floor
        beside it, which lies behind its plane as well (and every such floor pixel would otherwise be given the
        face's plane, and no light from the walls it faces)."""
        behind = np.zeros(points.shape[0], dtype=bool)
        rays = points / np.maximum(np.linalg.norm(points, axis=1, keepdims=True), 1e-12)
        for partner in self.facing[surface]:
            plane = self.planes[partner]
            within = np.linalg.norm(on_plane(rays, plane) - plane.centre, axis=1) <= HIDING_REACH * plane.visible_m
            behind |= (dot3(points - plane.centre, plane.normal) < 0) & within
        return behind

    def near_other_surface(self, coordinates: tuple[NDArray, NDArray], surface: NDArray, labels: NDArray
                           ) -> NDArray[np.bool_]:
        """Points (n,) on a plane whose value would be interpolated (at block coordinates ``coordinates``)
        from a block of another surface or of none: there the coupling changes faster than block values
        describe it."""
        hb, wb = labels.shape
        rows, columns = np.floor(coordinates[0]).astype(np.intp), np.floor(coordinates[1]).astype(np.intp)
        mixed = np.zeros(surface.shape, dtype=bool)
        for dy in (0, 1):
            for dx in (0, 1):
                mixed |= labels[np.clip(rows + dy, 0, hb - 1), np.clip(columns + dx, 0, wb - 1)] != surface
        return mixed & np.isin(surface, list(self.planes))


def _block_rays(scan: Scan, blocks: FacingBlocks) -> NDArray[np.float64]:
    """The unit ray (Hb*Wb, 3) through the centre pixel of every block."""
    hb, wb = blocks.usable.shape
    b = blocks.block_pixels
    h, w = blocks.shape
    ys, xs = np.meshgrid(np.minimum(np.arange(hb) * b + b // 2, h - 1), np.minimum(np.arange(wb) * b + b // 2, w - 1),
                         indexing="ij")
    return scan.pixel_rays(ys.ravel(), xs.ravel())


def _narrow_components(blocks: FacingBlocks, components: NDArray) -> set[int]:
    """Components fewer than :data:`MIN_SPAN_BLOCKS` blocks across their narrowest direction.

    The width is measured across the blocks' principal axis, not along the scan's rows or columns: the strip
    along an edge that is neither vertical nor horizontal runs diagonally through the block grid, where its
    extent in rows and in columns both exceed its width. A band w blocks wide has a variance (w^2 - 1) / 12
    across it.
    """
    wb = blocks.usable.shape[1]
    narrow = set()
    for component in np.unique(components[components >= 0]):
        rows, columns = np.divmod(np.flatnonzero(components == component), wb)
        spread = np.cov(np.stack([rows, columns]).astype(np.float64)) if rows.size > 1 else np.zeros((2, 2))
        if np.sqrt(12.0 * max(np.linalg.eigvalsh(spread)[0], 0.0) + 1.0) < MIN_SPAN_BLOCKS:
            narrow.add(int(component))
    return narrow


def _surface_planes(blocks: FacingBlocks, labels: NDArray, narrow: set[int]) -> dict[int, SurfacePlane]:
    """The plane of every flat surface that is not narrow, by surface label.

    The plane is the least-squares plane through the surface's block centres. The blocks' own normals would
    not do: fitted to 3 cm of noisy pixels whose noise runs along the rays, each tilts away from the ray
    (errors in variables), and their sum turned a 90-degree corner 2.4 m away (albedo 0.5) into 86.5
    degrees, whose coupling is 15 % stronger. The centres are means, free of that bias.
    """
    centres = blocks.centres.reshape(-1, 3)
    planes = {}
    for surface in np.unique(labels[labels >= 0]):
        if int(surface) in narrow:
            continue
        members = centres[labels == surface]
        centre = members.mean(0)
        normal = np.linalg.svd(members - centre, full_matrices=False)[2][-1]
        normal = -normal if normal @ centre > 0 else normal
        planes[int(surface)] = SurfacePlane(normal, centre, float(np.linalg.norm(members - centre, axis=1).max()))
    return planes


def _moved_plane(plane: SurfacePlane, fitted: NDArray) -> SurfacePlane:
    """A surface's plane moved onto the plane u . x = 1 (``fitted`` u [1/m]): its normal, and the visible centre
    projected onto it."""
    normal = -fitted / np.linalg.norm(fitted)  # u . x = 1 > 0 on the plane: -u points to the scanner
    return SurfacePlane(normal, plane.centre - (plane.centre @ fitted - 1.0) / (fitted @ fitted) * fitted,
                        plane.visible_m)


def _surface_patches(blocks: FacingBlocks, components: NDArray, planes: dict[int, SurfacePlane],
                     block_rays: NDArray, patch_m: float = PATCH_M, grading_m: float = GRADING_M
                     ) -> dict[int, Patches]:
    """The patches of every modelled surface's plane that faces another, by surface label, ``patch_m`` [m] wide next
    to a receiving surface and one such side wider every ``grading_m`` [m] further from it.

    Within the view a patch counts where the scan measured something at its range or behind it; beyond the view
    where the block nearest to its direction, on the view's border, shows the surface running on
    (:func:`_runs_on`). Neither counts behind the plane of a surface that bounds it (:func:`_bounding_surfaces`).
    """
    from scipy.spatial import cKDTree  # imported where used: the start-up does not pay for it

    block_range = np.where(blocks.usable.ravel(), np.linalg.norm(blocks.centres.reshape(-1, 3), axis=1), np.nan)
    directions = cKDTree(block_rays)
    # The second neighbour of each ray is the nearest other one (the first is the ray itself).
    spacing = float(np.median(directions.query(block_rays, k=2)[0][:, 1])) if block_rays.shape[0] > 1 else 0.0
    block_centres = blocks.centres.reshape(-1, 3)
    meeting = meeting_surfaces(blocks, components, set(planes))
    found = {}
    for surface, plane in planes.items():
        normal, centre = plane.normal, plane.centre
        receivers = blocks.usable.ravel() & np.isin(components, [other for other in planes if other != surface])
        if not receivers.any():
            continue
        reach_m = REACH * plane.visible_m
        e1 = np.cross(normal, [0.0, 1.0, 0.0] if abs(normal[1]) < 0.9 else [1.0, 0.0, 0.0])
        e1 /= np.linalg.norm(e1)
        e2 = np.cross(normal, e1)
        u, v, sides = _graded_patches(centre, e1, e2, reach_m, cKDTree(block_centres[receivers]), patch_m, grading_m)
        centres = centre + u[:, None] * e1 + v[:, None] * e2
        patch_range = np.linalg.norm(centres, axis=1)
        distance, nearest = directions.query(centres / np.maximum(patch_range, 1e-12)[:, None])
        outside = distance > 0.75 * spacing
        with np.errstate(invalid="ignore"):
            seen = ~outside & (patch_range >= _measured_range(centres / np.maximum(patch_range, 1e-12)[:, None],
                                                              nearest, blocks, block_range) - FRONT_TOLERANCE_M)
        others = meeting.get(surface, set())
        bounds = _bounding_surfaces(block_centres[components == surface], planes, others)
        continued = outside & _runs_on(centres, components[nearest], surface, planes, others, bounds)
        keep = (seen | continued) & (np.hypot(u, v) <= reach_m)
        for other in bounds:
            keep &= dot3(centres - planes[other].centre, planes[other].normal) > 0
        if keep.any():
            found[surface] = Patches(centres[keep], sides[keep] ** 2)
    return found


def _measured_range(rays: NDArray, nearest: NDArray, blocks: FacingBlocks, block_range: NDArray) -> NDArray:
    """The range [m] (m,) the scan measured along unit rays (m, 3) within the view: where a block seen at a grazing
    angle (the cosine of its normal with the ray under :data:`GRAZING_COSINE`) has its plane meet the ray, else that
    block's range ``block_range`` (its nearest block, ``nearest`` (m,); NaN for an unusable block).

    A block's centre stands for its ray alone: on a floor seen at a grazing angle the range changes by a decimetre
    across half a block, and a patch compared with the centre's range would read as lying in front of the floor
    it lies on (the holes then fall along the folds, where the coupling is strongest). A block seen more squarely
    (a corner's boards at 45 degrees) keeps its centre's range."""
    normals = blocks.normals.reshape(-1, 3)[nearest]
    along = np.einsum("ij,ij->i", rays, normals)
    offset = np.einsum("ij,ij->i", blocks.centres.reshape(-1, 3)[nearest], normals)
    grazing = (np.abs(along) > 0.1) & (np.abs(along) < GRAZING_COSINE)
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.where(grazing, offset / along, block_range[nearest])


def _bounding_surfaces(members: NDArray, planes: dict[int, SurfacePlane], meeting: set[int]) -> set[int]:
    """The surfaces of ``meeting`` that bound a surface of block centres ``members`` (k, 3) [m]: those whose plane
    has the whole of it in front (to :data:`FRONT_TOLERANCE_M`). A wall bounds its floor and the floor a box's face;
    a box's face, whose plane cuts through the floor it stands on, bounds neither."""
    return {other for other in meeting
            if members.size and dot3(members - planes[other].centre, planes[other].normal).min() > -FRONT_TOLERANCE_M}


def _runs_on(centres: NDArray, owner: NDArray, surface: int, planes: dict[int, SurfacePlane], meeting: set[int],
             bounds: set[int]) -> NDArray[np.bool_]:
    """Which patches (m, 3) [m] of ``surface``'s plane beyond the view continue the surface, given the surface
    ``owner`` (m,) of the border block nearest to each patch's direction: where the border shows the surface, or a
    surface it meets (``meeting``) that does not bound it (a box's face in front of a floor) or in front of whose
    plane the patch lies (a floor runs on beyond the view below the wall seen at the border)."""
    keep = owner == surface
    if not keep.any():  # the surface does not reach the view's border: it ends within the view
        return keep
    for other in meeting:
        if other in bounds:
            keep |= (owner == other) & (dot3(centres - planes[other].centre, planes[other].normal) > 0)
        else:
            keep |= owner == other
    return keep


def _graded_patches(centre: NDArray, e1: NDArray, e2: NDArray, reach_m: float, receivers: cKDTree,
                    patch_m: float = PATCH_M, grading_m: float = GRADING_M) -> tuple[NDArray, NDArray, NDArray]:
    """Square patches (u, v, side [m]) tiling the square of half-side ``reach_m`` around ``centre`` in the
    plane spanned by e1, e2: halved until each is at most ``patch_m`` (1 + d / ``grading_m``) wide, d the distance
    from the patch to the nearest receiving block centre (``receivers``)."""
    u, v, side = np.zeros(1), np.zeros(1), np.array([2 * reach_m])
    done: list[tuple[NDArray, NDArray, NDArray]] = []
    while u.size:
        points = centre + u[:, None] * e1 + v[:, None] * e2
        clearance = np.maximum(receivers.query(points)[0] - side / np.sqrt(2), 0.0)
        split = side > patch_m * (1 + clearance / grading_m)
        done.append((u[~split], v[~split], side[~split]))
        quarter = side[split] / 4
        u = np.concatenate([u[split] - quarter, u[split] + quarter, u[split] - quarter, u[split] + quarter])
        v = np.concatenate([v[split] - quarter, v[split] - quarter, v[split] + quarter, v[split] + quarter])
        side = np.tile(side[split] / 2, 4)
    u, v, side = (np.concatenate([patches[k] for patches in done]) for k in range(3))
    return u, v, side


def on_plane(rays: NDArray, plane: SurfacePlane) -> NDArray[np.float64]:
    """Points (n, 3) [m] where unit rays (n, 3) meet a plane (from its front)."""
    along = (plane.centre @ plane.normal) / np.minimum(dot3(rays, plane.normal), -1e-3)
    return rays * along[:, None]
