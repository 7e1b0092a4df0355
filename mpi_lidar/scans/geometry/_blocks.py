"""The grid of square pixel blocks a scan's geometry is fitted on: their size, the bands and tiles of whole blocks
worked on at once, a map cut into blocks and the median over each block's pixels."""

from __future__ import annotations

from typing import Protocol

import numpy as np
from numpy.typing import NDArray

# Pixels per tile of whole blocks that the plane fits work on at once (and per band of rows the potential
# is interpolated on): their float64 temporaries take about 300 bytes a pixel, so a tile bounds the memory
# whatever the scan's size.
BAND_PIXELS = 262_144
# Largest block side [px]. Blocks keep their metric size up to it, so a finer grid has bigger blocks, not
# more of them: the facing pairs grow with the square of the block count.
MAX_BLOCK_PIXELS = 512
# Smallest block side [px] for the metric size (a plane through 16 pixels keeps the noise of its normal small) and
# the side of the finer grid a coarse scan may be measured on (a plane still rests on 4 pixels).
MIN_BLOCK_PIXELS = 4
FINER_BLOCK_PIXELS = 2


class RayRowsLike(Protocol):
    """Unit rays (H, W, 3) read a band of rows at a time (``rays[top:bottom]``): an array or a scan's
    :class:`mpi_lidar.scans.scan.RayRows`, which builds each band only when asked."""

    @property
    def shape(self) -> tuple[int, ...]: ...

    def __getitem__(self, rows: slice, /) -> NDArray: ...


def block_size_pixels(depth: NDArray, rays: NDArray | RayRowsLike, block_m: float) -> int:
    """Side of a square pixel block spanning about ``block_m`` [m] at the scan's median range
    (:data:`MIN_BLOCK_PIXELS` to :data:`MAX_BLOCK_PIXELS`).

    ``rays`` (H, W, 3) may be anything that gives rows of rays by slicing (:class:`mpi_lidar.scans.scan.RayRows`):
    only the two centre rows are read.
    """
    return int(np.clip(_metric_block_pixels(depth, rays, block_m), MIN_BLOCK_PIXELS, MAX_BLOCK_PIXELS))


def finer_block_pixels(depth: NDArray, rays: NDArray | RayRowsLike, block_m: float) -> int | None:
    """:data:`FINER_BLOCK_PIXELS` where the scan is coarse, so that even :data:`MIN_BLOCK_PIXELS` of its pixels span
    more than ``block_m`` [m] (a room seen in a few dozen pixels: each surface is a handful of blocks, most of
    them along its folds); None elsewhere."""
    return FINER_BLOCK_PIXELS if _metric_block_pixels(depth, rays, block_m) < MIN_BLOCK_PIXELS else None


def _metric_block_pixels(depth: NDArray, rays: NDArray | RayRowsLike, block_m: float) -> int:
    """Pixels spanning ``block_m`` [m] at the scan's median range, rounded (:data:`MIN_BLOCK_PIXELS` where the
    scan gives no pitch)."""
    h, w = rays.shape[:2]
    cy, cx = h // 2, w // 2
    top = min(cy, max(h - 2, 0))
    r = np.asarray(rays[top:min(h, cy + 2)], dtype=np.float64)
    steps = []
    if w > 1:
        steps.append(np.arccos(np.clip(r[cy - top, min(cx, w - 2)] @ r[cy - top, min(cx, w - 2) + 1], -1, 1)))
    if h > 1:
        steps.append(np.arccos(np.clip(r[min(cy, h - 2) - top, cx] @ r[min(cy, h - 2) + 1 - top, cx], -1, 1)))
    values = np.asarray(depth)
    finite = values[np.isfinite(values) & (values > 0)]
    if not steps or finite.size == 0 or max(steps) <= 0:
        return MIN_BLOCK_PIXELS
    pitch_m = float(_median(finite)) * max(steps)
    return round(block_m / pitch_m)


def _median(values: NDArray) -> np.floating:
    """np.median of ``values`` taken in float64, without a float64 copy of them all (float32 widens exactly)."""
    n = values.size
    middle = np.partition(values.ravel(), [(n - 1) // 2, n // 2])[[(n - 1) // 2, n // 2]].astype(np.float64)
    return middle[0] if n % 2 else np.mean(middle)


def block_row_bands(height: int, width: int, block_pixels: int, band_pixels: int) -> list[slice]:
    """Row ranges of whole block rows, about ``band_pixels`` pixels each (at least one block row)."""
    rows = max(1, band_pixels // max(width * block_pixels, 1)) * block_pixels
    return [slice(top, min(top + rows, height)) for top in range(0, height, rows)]


def block_tiles(height: int, width: int, block_pixels: int, tile_pixels: int) -> list[list[tuple[slice, slice]]]:
    """Tiles of whole blocks, about ``tile_pixels`` pixels each (at least one block): per band of block rows,
    its (rows, columns) tiles from left to right."""
    tiles = []
    for rows in block_row_bands(height, width, block_pixels, tile_pixels):
        side = rows.stop - rows.start
        columns = max(1, tile_pixels // max(side * block_pixels, 1)) * block_pixels
        tiles.append([(rows, slice(left, min(left + columns, width))) for left in range(0, width, columns)])
    return tiles


def nanmedian_last(values: NDArray) -> NDArray[np.float64]:
    """np.nanmedian over the last axis, NaN where a row has only NaN, without its warnings.

    One sort of all rows at once (NaN sorts last) and the middle of each row's other values: the same
    numbers as np.nanmedian, which works row by row and costs ten times as much on blocks of a few hundred.
    """
    ordered = np.sort(values, axis=-1)
    count = (~np.isnan(values)).sum(-1, keepdims=True)
    low = np.take_along_axis(ordered, np.maximum(count - 1, 0) // 2, axis=-1)
    high = np.take_along_axis(ordered, np.minimum(count // 2, values.shape[-1] - 1), axis=-1)
    return np.where(count > 0, (low + high) / 2, np.nan)[..., 0]


def to_blocks(values: NDArray, b: int) -> NDArray:
    """(H, W, ...) -> (Hb, Wb, b*b, ...), padded with NaN to whole blocks."""
    h, w = values.shape[:2]
    hb, wb = -(-h // b), -(-w // b)
    padded = np.full((hb * b, wb * b, *values.shape[2:]), np.nan)
    padded[:h, :w] = values
    shaped = padded.reshape(hb, b, wb, b, *values.shape[2:]).swapaxes(1, 2)
    return shaped.reshape(hb, wb, b * b, *values.shape[2:])

