"""A scan's amplitude maps in V^2 without a second copy of them (:class:`AmplitudeInV2`).

A scan whose amplitudes come in the scanner's own unit is read in V^2 by every stage after the unit is measured:
the validity rules, the albedo, the footprint and the model's inputs. Dividing the maps once would make a copy of
F x H x W float32 (244 MiB at 4000 x 4000 pixels and four frequencies), which took such a scan past 1 GiB; the
maps are read as they are (from memory or from the store) and divided as they are read.
"""

from __future__ import annotations

from typing import Any

import numpy as np
from numpy.typing import NDArray

from mpi_lidar.scans.stored_map import StoredMap


class AmplitudeInV2:
    """Amplitude maps (F, H, W) in the scanner's unit, read divided by ``units_per_v2`` [unit / V^2]: it reads like
    the maps (``shape``, ``dtype``, ``ndim``, ``np.asarray``, any index the maps take), each value float32 and equal
    to the map's value divided in float64. No state changes on reading: threads may share it."""

    def __init__(self, measured: NDArray | StoredMap, units_per_v2: float):
        self.measured, self.units_per_v2 = measured, float(units_per_v2)
        self.shape: tuple[int, ...] = tuple(measured.shape)
        self.ndim = len(self.shape)
        self.dtype = np.dtype(np.float32)
        # Where the maps are read from: a stored map is read a band at a time, by one thread (Scan.in_memory).
        self.in_store = isinstance(measured, StoredMap)

    def __array__(self, dtype: np.dtype | None = None, copy: bool | None = None) -> NDArray:
        return np.asarray(self._divided(np.asarray(self.measured)), dtype=dtype)

    def __getitem__(self, key: Any) -> NDArray[np.float32]:
        return self._divided(np.asarray(self.measured[key]))

    def _divided(self, values: NDArray) -> NDArray[np.float32]:
        return (values / self.units_per_v2).astype(np.float32)
