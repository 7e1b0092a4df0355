"""Rendered scenes the calibration tests share: boards facing the sensor, each render made once per session."""

from __future__ import annotations

import dataclasses

import numpy as np

from mpi_lidar.config import Config, SensorConfig
from mpi_lidar.correction import CorrectionOptions, validity_flags
from mpi_lidar.correction.sensor_reading import read_sensor
from mpi_lidar.correction.validity import usable_depth_of
from mpi_lidar.scans.scan import Scan
from mpi_lidar.simulation.scenes import Rectangle, Scene, render

SENSOR = SensorConfig()
# Depth rules alone (finite, frequencies consistent): amplitude thresholds in V^2 would call a scan in other units
# saturated (x 4000) or dark (x 0.01).
DEPTH_RULES = CorrectionOptions(min_amplitude_sigmas=0.0, saturation_amplitude_v2=1e30)


def board(centre: tuple[float, float, float], half_width_m: float, half_height_m: float, albedo: float,
          yaw_deg: float = 0.0) -> Rectangle:
    """A one-sided board facing the sensor, turned by ``yaw_deg`` about the vertical: its normal
    (sin yaw, 0, -cos yaw) never faces another such board behind or before it, so no board sends light to another."""
    yaw = np.deg2rad(yaw_deg)
    return Rectangle(centre, (half_width_m * np.cos(yaw), 0.0, half_width_m * np.sin(yaw)), (0.0, -half_height_m, 0.0),
                     albedo, two_sided=False)


def boards_scene() -> Scene:
    """Five boards from 0.6 m to 2.6 m, two of them turned, albedos 0.3-0.9: amplitudes from 0.01 to 0.45 V^2, from
    where thermal noise rules to where shot noise does."""
    boards = (board((-0.17, 0.0, 0.6), 0.08, 0.1, 0.9), board((0.2, 0.0, 0.9), 0.12, 0.18, 0.5, yaw_deg=30),
              board((-0.55, 0.0, 1.5), 0.2, 0.3, 0.3), board((0.75, 0.0, 2.0), 0.25, 0.4, 0.9, yaw_deg=-40),
              board((0.0, 0.0, 2.6), 1.2, 0.6, 0.45))
    return Scene("boards", boards, np.linspace(-0.4, 0.4, 240), np.linspace(0.2, -0.2, 120))


_RENDERS: dict[tuple, tuple[Scan, dict[str, np.ndarray]]] = {}


def rendered(scene: Scene, seed: int = 1, truth_out: dict | None = None, patch_spacing_m: float | None = None,
             **simulator: object) -> Scan:
    """A render of ``scene`` with the simulator options given, once per session (the boards with coarse partner
    patches: they face no other board); ``truth_out`` receives the render's true multipath."""
    if scene.name == "boards":
        patch_spacing_m = 0.25
    key = (scene.name, scene.azimuth_rad.tobytes(), seed, patch_spacing_m, tuple(sorted(simulator.items())))
    if key not in _RENDERS:
        truth: dict[str, np.ndarray] = {}
        config = Config().replace(simulator=simulator)
        scan = render(scene, config, np.random.default_rng(seed), patch_spacing_m=patch_spacing_m, truth_out=truth)
        _RENDERS[key] = (scan, truth)
    scan, truth = _RENDERS[key]
    if truth_out is not None:
        truth_out.update(truth)
    return scan


def depth_usable(scan: Scan) -> np.ndarray:
    """Highest-frequency depth (H*W,) of the pixels the depth rules alone keep, NaN elsewhere. [m]"""
    raw = scan.raw_pixels()
    # The scan's own noise law in its own unit: the consistency test needs no other.
    noise = read_sensor(scan, SENSOR, CorrectionOptions(amplitude_scale=1.0)).noise
    return usable_depth_of(raw, validity_flags(raw, DEPTH_RULES, noise))


def in_units(scan: Scan, units_per_v2: float) -> Scan:
    """The scan with its amplitudes in a unit of ``units_per_v2`` per V^2."""
    return dataclasses.replace(scan, amplitude=(scan.amplitude * units_per_v2).astype(np.float32))
