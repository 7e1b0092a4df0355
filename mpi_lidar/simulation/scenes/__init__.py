"""Scene simulator: scans of simple geometric scenes through the coaxial scanning geometry.

A scene is a few surfaces (rectangles, spheres, cylinders, prisms) and the scan grid that looks at them;
:func:`render` traces the first surface of each scan direction, integrates the two-path multipath over
patches of the other surfaces (:func:`light_transport`) and passes the phasors through the sensor model,
keeping the exact reference depth. :data:`SCENES` names the scenes after the paper's figures;
:func:`scan_from_phasors` and :func:`scan_from_transient` take externally rendered light instead.

The parts, each private: ``_geometry`` (surfaces, the scene, first hits), ``_transport`` (the light
transport and its derivation), ``_multibounce`` (multi-bounce light transport with occlusion, for scenes whose
notes ask for ``bounces``), ``_render`` (the sensor and the reference), ``_catalogue`` (the named scenes),
``_room`` (room corners: walls, floor, ceiling and a box) and ``_external`` (external renders).
"""

from __future__ import annotations

from mpi_lidar.physics.coupling import DEFAULT_COUPLING_GAIN, DEFAULT_FOOTPRINT_RADIUS_M
from mpi_lidar.simulation.scenes._catalogue import (
    DEMO_SCENES,
    SCENES,
    alcove,
    box_on_floor,
    corner,
    cornered_board,
    cylinder_scene,
    flat_wall,
    floor_meets_wall,
    multi_object,
    pitch_rotation,
    render_scenes,
    room_corner,
    sphere_scene,
    wooden_corner,
)
from mpi_lidar.simulation.scenes._external import scan_from_phasors, scan_from_transient
from mpi_lidar.simulation.scenes._geometry import Cylinder, Rectangle, Scene, Sphere, Surface, first_hits, prism
from mpi_lidar.simulation.scenes._render import DEFAULT_PATCH_SPACING_M, render, sense, simple_region_mask
from mpi_lidar.simulation.scenes._room import room_with_box, turned_room_with_box
from mpi_lidar.simulation.scenes._transport import light_transport

__all__ = [
    "DEFAULT_COUPLING_GAIN", "DEFAULT_FOOTPRINT_RADIUS_M", "DEFAULT_PATCH_SPACING_M", "DEMO_SCENES", "SCENES",
    "Cylinder", "Rectangle", "Scene", "Sphere", "Surface", "alcove", "box_on_floor", "corner", "cornered_board",
    "cylinder_scene", "first_hits", "flat_wall", "floor_meets_wall", "light_transport", "multi_object",
    "pitch_rotation", "prism", "render", "render_scenes", "room_corner", "room_with_box", "scan_from_phasors",
    "scan_from_transient", "sense", "simple_region_mask", "sphere_scene", "turned_room_with_box", "wooden_corner",
]
