"""Room corners: two walls and a floor (and a ceiling) meeting in tri-corners, with a box on the floor, rendered
with multi-bounce light transport and occlusion (:mod:`._multibounce`).

The room is built in its own frame (y up, the floor at y = 0, the walls on the planes z = 0 and x = 0, the
tri-corner at the origin, the room where x, z > 0) and turned into the sensor's frame, whose view axis is z.
Every face is one-sided: the walls, floor and ceiling send light into the room, the box's faces out of it.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from mpi_lidar.physics.coupling import DEFAULT_COUPLING_GAIN
from mpi_lidar.simulation.scenes._geometry import Rectangle, Scene
from mpi_lidar.simulation.scenes._multibounce import DEFAULT_BOUNCES

# The rooms' patch spacing [m] next to another surface: 3 cm keeps a 48 x 64 render to a few seconds.
ROOM_PATCH_SPACING_M = 0.03

Point = tuple[float, float, float]
Segment = tuple[Point, Point]


def _face(corner: NDArray, along_u: NDArray, along_v: NDArray, inward: NDArray, albedo: float) -> Rectangle:
    """The one-sided rectangle spanned from ``corner`` by ``along_u`` and ``along_v`` [m], sending light towards
    ``inward``."""
    half_u, half_v = along_u / 2, along_v / 2
    centre = corner + half_u + half_v
    if np.cross(half_u, half_v) @ inward < 0:
        half_v = -half_v
    return Rectangle(tuple(centre), tuple(half_u), tuple(half_v), albedo, two_sided=False)


def room_surfaces(size_m: tuple[float, float, float], ceiling: bool, box_corner: tuple[float, float],
                  box_m: float, albedo: float) -> tuple[list[Rectangle], list[Segment], list[Point]]:
    """The room's faces in its own frame, its concave folds (segments where two faces meet, box and floor
    included) and its tri-corners (points where three faces meet).

    ``size_m`` is the extent along x, y (the height) and z [m]; ``box_corner`` the box's (x, z) corner nearest
    the tri-corner [m] and ``box_m`` its side [m].
    """
    lx, height, lz = size_m
    x, y, z = np.eye(3)
    o = np.zeros(3)
    faces = [_face(o, lx * x, height * y, z, albedo),  # the wall on z = 0
             _face(o, lz * z, height * y, x, albedo),  # the wall on x = 0
             _face(o, lx * x, lz * z, y, albedo)]  # the floor
    folds: list[Segment] = [((0, 0, 0), (lx, 0, 0)), ((0, 0, 0), (0, 0, lz)), ((0, 0, 0), (0, height, 0))]
    tri_corners: list[Point] = [(0, 0, 0)]
    if ceiling:
        faces.append(_face(height * y, lx * x, lz * z, -y, albedo))
        folds += [((0, height, 0), (lx, height, 0)), ((0, height, 0), (0, height, lz))]
        tri_corners.append((0, height, 0))
    bx, bz = box_corner
    base = np.array([bx, 0.0, bz])
    up = box_m * y
    faces += [_face(base, box_m * x, up, -z, albedo), _face(base, box_m * z, up, -x, albedo),
              _face(base + box_m * z, box_m * x, up, z, albedo), _face(base + box_m * x, box_m * z, up, x, albedo),
              _face(base + up, box_m * x, box_m * z, y, albedo)]
    corners = [base, base + box_m * x, base + box_m * x + box_m * z, base + box_m * z]
    folds += [(tuple(corners[k]), tuple(corners[(k + 1) % 4])) for k in range(4)]  # the box meets the floor
    return faces, folds, tri_corners


def view_rotation(eye: NDArray, target: NDArray) -> NDArray[np.float64]:
    """The rotation (3, 3) from the room's frame into the frame of a sensor at ``eye`` looking at ``target``
    (its z along the view, its y as near the room's up as the view allows)."""
    forward = (target - eye) / np.linalg.norm(target - eye)
    right = np.cross([0.0, 1.0, 0.0], forward)
    right /= np.linalg.norm(right)
    return np.stack([right, np.cross(forward, right), forward])


def room_with_box(turn_deg: float = 0.0, ceiling: bool = False, eye_height_m: float = 0.6,
                  distance_m: float = 2.0, albedo: float = 0.7, height: int = 48, width: int = 64, *,
                  bounces: int = DEFAULT_BOUNCES, footprint_m2: float | None = None) -> Scene:
    """A room corner seen from ``distance_m`` (horizontally) [m]: two walls and the floor meeting in a tri-corner
    and a 0.35 m box on the floor beside it, all of albedo ``albedo``, the sensor ``eye_height_m`` [m] above the
    floor.

    At ``turn_deg`` = 0 the sensor stands on the corner's bisector and looks at the tri-corner; otherwise the room
    is turned by ``turn_deg`` about the vertical edge. With a ``ceiling`` (1.3 m above the floor) the walls also
    meet it in a second tri-corner and the sensor looks at the edge halfway between the two, with a wider view.
    The scene's :attr:`Scene.folds` and :attr:`Scene.tri_corners` (sensor frame) mark where the faces meet.
    ``footprint_m2`` is the effective receiver footprint [m^2] :func:`render` gives it (None: the renderer's own).
    """
    size = (2.2, 1.3 if ceiling else 1.2, 2.2)
    box_corner = (0.75, 0.15) if not ceiling else (0.6, 0.15)
    faces, folds, tri_corners = room_surfaces(size, ceiling, box_corner, 0.35, albedo)
    bearing = np.deg2rad(45.0 + turn_deg)
    eye = np.array([distance_m * np.cos(bearing), eye_height_m, distance_m * np.sin(bearing)])
    target = np.array([0.0, size[1] / 2 if ceiling else 0.0, 0.0])
    turn = view_rotation(eye, target)

    def to_view(point: NDArray | Point) -> Point:
        return tuple(turn @ (np.asarray(point, dtype=np.float64) - eye))

    surfaces = tuple(Rectangle(to_view(f.centre), tuple(turn @ np.asarray(f.half_u)),
                               tuple(turn @ np.asarray(f.half_v)), f.albedo, two_sided=False) for f in faces)
    half_width, half_height = (0.68, 0.51) if ceiling else (0.3, 0.225)
    azimuth = np.linspace(-half_width, half_width, width)
    elevation = np.linspace(half_height, -half_height, height)  # row 0 is the top
    name = f"room_box_turned{turn_deg:g}deg" if turn_deg else "room_box"
    notes = {"bounces": float(bounces), "patch_spacing_m": ROOM_PATCH_SPACING_M, "turn_deg": turn_deg}
    if footprint_m2 is not None:
        notes["footprint_radius_m"] = float(np.sqrt(footprint_m2 / (DEFAULT_COUPLING_GAIN * np.pi)))
    return Scene(name, surfaces, azimuth, elevation, notes=notes,
                 folds=tuple((to_view(a), to_view(b)) for a, b in folds),
                 tri_corners=tuple(to_view(p) for p in tri_corners))


def turned_room_with_box(height: int = 48, width: int = 64, *, bounces: int = DEFAULT_BOUNCES,
                         footprint_m2: float | None = None) -> Scene:
    """The room turned 35 degrees, with a ceiling (a wall-wall-ceiling tri-corner too), the sensor 0.8 m above the
    floor (:func:`room_with_box`)."""
    return room_with_box(35.0, True, 0.8, height=height, width=width, bounces=bounces, footprint_m2=footprint_m2)
