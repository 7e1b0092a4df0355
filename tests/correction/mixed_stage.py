"""The mixed-pixel stage run as the correction runs it, for the mixed-pixel tests."""

from __future__ import annotations

import numpy as np

from mpi_lidar.config import SensorConfig
from mpi_lidar.correction.gating import GateDecision
from mpi_lidar.correction.mixed import find_mixed
from mpi_lidar.correction.options import CorrectionOptions, Flag
from mpi_lidar.correction.tiles import scan_tiles
from mpi_lidar.correction.validity import check_validity
from mpi_lidar.physics.noise import NoiseModel


def mixed_stage(scan):
    """The stage's result, the gate's decision it was handed, its flags (H, W) and the validity stage's result, read
    in tiles of four rows (every pixel the gate would leave alone handed over as `no_multipath`)."""
    noise = NoiseModel.for_sensor(SensorConfig(), scan.frequencies_hz)
    tiles = scan_tiles(scan, 4 * scan.shape[1])
    validity = check_validity(scan, noise, CorrectionOptions(), tiles)
    flags = np.where(validity.flags == Flag.NOT_NEEDED, np.uint8(Flag.NO_MULTIPATH), validity.flags)
    decision = GateDecision(flags.astype(np.uint8), 0, served=True)
    result = find_mixed(validity.scan, tiles, validity, decision, noise)
    return result, decision, result.decision.flags.reshape(scan.shape), validity
