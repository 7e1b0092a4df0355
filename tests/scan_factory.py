"""Small scans built pixel by pixel from two-path scene parameters, for correction tests."""

from __future__ import annotations

import numpy as np

from mpi_lidar.config import Config
from mpi_lidar.physics import make_sensor
from mpi_lidar.physics.demod import depth_and_amplitude
from mpi_lidar.scans.scan import Scan


def two_path_scan(name: str, height: int = 24, width: int = 32, multipath: bool = True, seed: int = 0,
                  config: Config | None = None, near_m: float = 2.0, albedo: float = 0.7) -> Scan:
    """A tilted wall from ``near_m`` to 10 cm farther whose left half has multipath (d_AB growing to the
    right), with geometry; every reflection has the ``albedo``."""
    config = config or Config()
    depth_true = near_m + 0.1 * np.linspace(0, 1, width)[None, :].repeat(height, 0)
    theta = np.zeros((height * width, 6))
    theta[:, 0] = depth_true.ravel()
    theta[:, 1] = np.tile(np.linspace(0.0, 0.15, width), height)
    theta[:, 2:] = albedo
    theta[:, 4] = albedo * multipath * (np.tile(np.arange(width), height) < width // 2)
    taps = make_sensor(config).taps(theta, np.random.default_rng(seed))
    depth, amplitude = depth_and_amplitude(taps, config.frequencies_hz, config.sensor.speed_of_light_m_per_s)
    f = len(config.frequencies_hz)
    return Scan(
        name=name, frequencies_hz=config.frequencies_hz,
        depth=depth.T.reshape(f, height, width).astype(np.float32),
        amplitude=amplitude.T.reshape(f, height, width).astype(np.float32),
        azimuth_rad=np.linspace(-0.2, 0.2, width), elevation_rad=np.linspace(-0.15, 0.15, height),
        reference_depth=depth_true.astype(np.float32), reference_mask=np.ones((height, width), bool),
        speed_of_light_m_per_s=config.sensor.speed_of_light_m_per_s,
    )


def inverse_variance_mean(scan: Scan, offsets_m: tuple[float, ...] | None = None, window: bool = False) -> np.ndarray:
    """Each pixel's frequencies' depths less their ``offsets_m`` (F,) [m] (and with the integration window's leakage
    removed first where ``window``), averaged with weights 1 / sd^2 of the noise model at their amplitudes, (H, W)
    [m]: the fused depth, worked out here directly from the scan's maps."""
    from mpi_lidar.config import SensorConfig
    from mpi_lidar.physics.noise import depth_noise_m
    from mpi_lidar.physics.window import window_corrections_m

    f = len(scan.frequencies_hz)
    depth = np.asarray(scan.depth, dtype=np.float64).reshape(f, -1).T - np.asarray(offsets_m or np.zeros(f))
    amplitude = np.asarray(scan.amplitude, dtype=np.float64).reshape(f, -1).T
    if window:
        depth += window_corrections_m(depth, amplitude, tuple(scan.frequencies_hz), SensorConfig())
    weight = 1.0 / depth_noise_m(SensorConfig(), tuple(scan.frequencies_hz), np.maximum(amplitude, 1e-12)) ** 2
    return ((weight * depth).sum(1) / weight.sum(1)).reshape(scan.shape)
