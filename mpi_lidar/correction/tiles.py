"""How a scan's pixels are read for correction: tiles of whole rows, their raw measurements, and stage clocks.

Everything per pixel runs tile by tile, so its working memory is that of one tile whatever the scan's size. A scan
kept in its store (:class:`~mpi_lidar.scans.stored_map.StoredMap`) decodes each band of rows once per pass that
reads it: the correction reads every tile twice, once before the scene geometry and once after.
"""

from __future__ import annotations

import ctypes
import time
from collections.abc import Iterator
from contextlib import contextmanager, suppress
from dataclasses import replace
from typing import cast

import numpy as np
from numpy.typing import NDArray

from mpi_lidar.correction.amplitude_in_v2 import AmplitudeInV2
from mpi_lidar.correction.unwrapped_depth import UnwrappedDepth
from mpi_lidar.scans.scan import Scan
from mpi_lidar.scans.stored_map import StoredMap

# Rows of a tile's per-pixel work (validity, the model's inputs) that one thread takes at least: NumPy
# releases the GIL in its loops, so a tile's rows are split among the cores, each row computed as alone.
PARALLEL_MIN_ROWS = 16_384


def row_tiles(height: int, width: int, tile_pixels: int) -> list[slice]:
    """Flat pixel ranges of whole rows, about ``tile_pixels`` each (at least one row)."""
    rows = max(1, tile_pixels // max(width, 1))
    return [slice(top * width, min(top + rows, height) * width) for top in range(0, height, rows)]


def scan_tiles(scan: Scan, tile_pixels: int) -> list[slice]:
    """:func:`row_tiles` of a scan; for one kept in its store, those of each band of rows its maps are read in
    (:meth:`StoredMap.row_bands`), so that no tile spans two bands: a stored map keeps the last band it read,
    and a tile across two would have it read a band of twice the rows, decoding the rows it shares with the
    bands on either side once more."""
    h, w = scan.shape
    if not isinstance(scan.amplitude, StoredMap):
        return row_tiles(h, w, tile_pixels)
    return [slice(band.start * w + tile.start, band.start * w + tile.stop)
            for band in scan.amplitude.row_bands() for tile in row_tiles(band.stop - band.start, w, tile_pixels)]


def raw_tiles(scan: Scan, tiles: list[slice]) -> Iterator[tuple[slice, NDArray[np.float32]]]:
    """(pixels, raw measurements (n, 2F) of those pixels) per tile, built from the maps' rows as needed."""
    w = scan.shape[1]
    for pixels in tiles:
        rows = slice(pixels.start // w, pixels.stop // w)
        yield pixels, replace(scan, depth=scan.depth[:, rows], amplitude=scan.amplitude[:, rows]).raw_pixels()


def in_v2(scan: Scan, units_per_v2: float) -> Scan:
    """The scan with its amplitudes divided by the scanner's unit per V^2 as they are read (no copy of the maps)."""
    if units_per_v2 == 1.0:
        return scan
    return replace(scan, amplitude=cast("NDArray[np.float32]", AmplitudeInV2(scan.amplitude, units_per_v2)))


def unwrapped_scan(scan: Scan, pixels: NDArray[np.intp], depths: NDArray[np.float32]) -> Scan:
    """The scan with its depth maps unwrapped into one range: the scene geometry, the footprint and the model all
    read depths. The maps are read as measured, the unwrapped depths of the pixels that moved (flat indices
    ``pixels`` (k,), ascending, ``depths`` (k, F) [m], kept by the validity pass) put in as they are read
    (:class:`UnwrappedDepth`); only where those would take more memory than the maps is a copy of the maps
    made, in memory (F x H x W float32, also for a scan kept in its store)."""
    unwrapped = UnwrappedDepth(scan.depth, pixels, depths)
    if pixels.nbytes + depths.nbytes > 4 * np.prod(scan.depth.shape, dtype=np.float64):
        return replace(scan, depth=unwrapped.whole(), depth_wrapped=False)
    return replace(scan, depth=cast("NDArray[np.float32]", unwrapped), depth_wrapped=False)


def release_freed_memory() -> None:
    """Give the pages of the C heap that a stage freed back to the system (glibc; elsewhere nothing is done).

    A stage's tiles leave their freed working memory in the heap, resident: the next stage's large arrays, mapped
    afresh, come on top of it, and the outputs' writing on top of the per-pixel estimate's (41 MiB of a 4000 x 4000
    scan's peak). Returning the pages changes no value; it costs a walk over the heap.
    """
    with suppress(OSError, AttributeError):  # no C library to load, or one without malloc_trim (macOS, musl)
        ctypes.CDLL(None).malloc_trim(0)


class StageClock:
    """CPU seconds of this process (every thread) per named stage, summed over tiles."""

    def __init__(self) -> None:
        self.seconds: dict[str, float] = {}

    def add(self, stage: str, seconds: float) -> None:
        self.seconds[stage] = self.seconds.get(stage, 0.0) + seconds

    @contextmanager
    def __call__(self, stage: str) -> Iterator[None]:
        started = time.process_time()
        try:
            yield
        finally:
            self.add(stage, time.process_time() - started)
