"""Pure numpy physics of the AMCW coaxial scanning LiDAR, SI units throughout."""

from __future__ import annotations

from mpi_lidar.config import Config
from mpi_lidar.physics.moments import MomentSensor
from mpi_lidar.physics.sensor import SensorModel, WaveformSensor

FIDELITIES: dict[str, type[SensorModel]] = {"moment": MomentSensor, "waveform": WaveformSensor}


def make_sensor(config: Config) -> SensorModel:
    """The simulator of the configured fidelity (``moment`` by default, ``waveform`` for the faithful one)."""
    return FIDELITIES[config.simulator.fidelity](config)


__all__ = ["FIDELITIES", "MomentSensor", "SensorModel", "WaveformSensor", "make_sensor"]
