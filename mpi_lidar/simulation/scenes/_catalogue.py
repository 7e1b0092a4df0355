"""The named scenes: corners, walls, rooms and objects after the paper's figures, and rendering them to disk."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import replace
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from mpi_lidar.config import Config
from mpi_lidar.scans.store import write_scan
from mpi_lidar.simulation.scenes._geometry import Cylinder, Rectangle, Scene, Sphere, prism
from mpi_lidar.simulation.scenes._render import render
from mpi_lidar.simulation.scenes._room import room_with_box, turned_room_with_box


def _grid(height: int, width: int, half_width_rad: float, half_height_rad: float,
          centre_az_rad: float = 0.0) -> tuple[NDArray, NDArray]:
    azimuth = centre_az_rad + np.linspace(-half_width_rad, half_width_rad, width)
    elevation = np.linspace(half_height_rad, -half_height_rad, height)  # row 0 is the top
    return azimuth, elevation


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
    "room_box": room_with_box, "room_box_turned": turned_room_with_box,  # multi-bounce, with occlusion
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
