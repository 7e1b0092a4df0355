"""Rendering a scene: its light transport through the sensor model, with the exact reference depth."""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from mpi_lidar.config import Config
from mpi_lidar.physics import demod, make_sensor
from mpi_lidar.physics.coupling import DEFAULT_COUPLING_GAIN, DEFAULT_FOOTPRINT_RADIUS_M
from mpi_lidar.physics.sensor import received_voltage_amplitude
from mpi_lidar.scans.scan import Scan
from mpi_lidar.simulation.scenes._geometry import Scene, first_hits
from mpi_lidar.simulation.scenes._transport import light_transport

DEFAULT_PATCH_SPACING_M = 0.02


def render(scene: Scene, config: Config, rng: np.random.Generator, *,
           footprint_radius_m: float | None = None,
           patch_spacing_m: float | None = None, coupling_gain: float = DEFAULT_COUPLING_GAIN,
           truth_out: dict[str, NDArray] | None = None) -> Scan:
    """Render a scan: exact reference depth, two-path-per-patch light transport, then the sensor model.

    ``patch_spacing_m`` defaults to the scene's own (large scenes use coarser patches) or 2 cm, and
    ``footprint_radius_m`` to the scene's own (its notes) or :data:`DEFAULT_FOOTPRINT_RADIUS_M`. A dict passed
    as ``truth_out`` receives the render's true multipath per pixel (:func:`light_transport`'s
    ``coupling_out``).
    """
    patch_spacing_m = patch_spacing_m or float(scene.notes.get("patch_spacing_m", DEFAULT_PATCH_SPACING_M))
    if footprint_radius_m is None:
        footprint_radius_m = float(scene.notes.get("footprint_radius_m", DEFAULT_FOOTPRINT_RADIUS_M))
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
        speed_of_light_m_per_s=config.sensor.speed_of_light_m_per_s,
        scene={"scene": scene.name, "surfaces": len(scene.surfaces), "coupling_gain": coupling_gain, **scene.notes,
               "footprint_radius_m": footprint_radius_m, "patch_spacing_m": patch_spacing_m},
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


def sense(phasor: NDArray, dc: NDArray, config: Config, rng: np.random.Generator) -> tuple[NDArray, NDArray]:
    """Depth (F, N) [m] and amplitude (F, N) [V^2] of correlation phasors (N, F) through the sensor model."""
    s = config.sensor
    to_volts = received_voltage_amplitude(1.0, s.modulation_contrast, s.demodulation_amplitude_v)
    taps = make_sensor(config).taps_from_phasors(dc * to_volts, phasor * to_volts, rng)
    depth, amplitude = demod.depth_and_amplitude(taps, config.frequencies_hz, s.speed_of_light_m_per_s)
    return depth.T, amplitude.T
