"""A scan's depth maps unwrapped into one range without a second copy of them (:class:`UnwrappedDepth`).

Correction unwraps every pixel once, in its validity pass; the scene geometry, the footprint and the model read
the depths again afterwards. A copy of the maps with the unwrapped depths filled in is F x H x W float32 (244 MiB
at 4000 x 4000 pixels and four frequencies, the largest array of a correction), while only the pixels beyond the
highest frequency's ambiguity distance take a wrap count. So the maps are read as measured (from memory or from
the store) and the depths of those pixels are put in as they are read.
"""

from __future__ import annotations

from typing import cast

import numpy as np
from numpy.typing import NDArray

from mpi_lidar.scans.stored_map import StoredMap


class UnwrappedDepth:
    """Depth maps (F, H, W) [m] as measured, with the depths of the pixels that took a wrap count replaced by their
    unwrapped ones: it reads like the maps (``shape``, ``dtype``, ``ndim``, ``np.asarray``).

    Indexing as correction reads a scan's depths: ``[f, rows, columns]`` with an integer or a slice for the
    frequencies and unit-step slices or integers for rows and columns (``[:, rows]`` too), or ``[f, ys, xs]``
    with integer arrays (n,) of rows and columns, which gives (F, n) (or (n,) for one frequency). Every value
    is that of :meth:`whole` at the same index. No state changes on reading: threads may share it.
    """

    def __init__(self, measured: NDArray, pixels: NDArray, depths: NDArray):
        """``measured`` (F, H, W): the maps as measured [m] (an array or a
        :class:`~mpi_lidar.scans.stored_map.StoredMap`); ``pixels`` (k,): the flat indices of the pixels that
        took a wrap count, ascending; ``depths`` (k, F): their unwrapped depths [m]."""
        self.measured, self.pixels, self.depths = measured, pixels, depths
        self.shape: tuple[int, ...] = tuple(measured.shape)
        self.ndim = len(self.shape)
        self.dtype = np.dtype(np.float32)
        # Where the maps are read from: a stored map is read a band at a time, by one thread (Scan.in_memory).
        self.in_store = isinstance(measured, StoredMap)

    def __array__(self, dtype: np.dtype | None = None, copy: bool | None = None) -> NDArray:
        return np.asarray(self.whole(), dtype=dtype)

    def whole(self) -> NDArray[np.float32]:
        """All of the maps (F, H, W) in memory."""
        f = self.shape[0]
        values = np.array(self.measured, dtype=np.float32).reshape(f, -1)
        values[:, self.pixels] = self.depths.T
        return values.reshape(self.shape)

    def __getitem__(self, key: object) -> NDArray:
        key = key if isinstance(key, tuple) else (key,)
        if len(key) > 3 or any(k is Ellipsis for k in key):
            raise IndexError(f"unwrapped depths are read as [frequencies, rows, columns], got {key!r}")
        padded: tuple[object, ...] = key + (slice(None),) * (3 - len(key))
        frequencies, rows, columns = padded
        if isinstance(rows, np.ndarray) or isinstance(columns, np.ndarray):
            return self._picked(frequencies, np.asarray(rows), np.asarray(columns))
        return self._box(frequencies, rows, columns)

    def _box(self, frequencies: object, rows: object, columns: object) -> NDArray:
        """The values of whole rows and columns; an integer index drops its axis, as NumPy's does."""
        box = (_one_long(frequencies, self.shape[0], any_step=True), _one_long(rows, self.shape[1]),
               _one_long(columns, self.shape[2]))
        values = self.measured[box]
        w = self.shape[2]
        first, last = np.searchsorted(self.pixels, [box[1].start * w, box[1].stop * w])
        y, x = np.divmod(self.pixels[first:last], w)
        inside = (x >= box[2].start) & (x < box[2].stop)
        if inside.any():
            values = np.array(values)  # the measured maps (or a stored map's band of rows) stay as they are
            values[:, y[inside] - box[1].start, x[inside] - box[2].start] = self.depths[first:last][inside][:, box[0]].T
        return values[tuple(0 if _is_integer(k) else slice(None) for k in (frequencies, rows, columns))]

    def _picked(self, frequencies: object, ys: NDArray, xs: NDArray) -> NDArray:
        """The values of pixels at rows ``ys`` and columns ``xs`` (n,): (F', n), or (n,) for one frequency."""
        if ys.ndim != 1 or ys.shape != xs.shape:
            raise IndexError("unwrapped depths pick pixels by rows and columns of one dimension and the same size")
        values = np.asarray(self.measured[:, ys, xs])  # every frequency: a stored map picks no fewer
        h, w = self.shape[1:]
        flat = (ys % h) * w + xs % w
        at = np.minimum(np.searchsorted(self.pixels, flat), max(self.pixels.size - 1, 0))
        hit = np.flatnonzero(self.pixels[at] == flat) if self.pixels.size else at[:0]
        if hit.size:
            values = np.array(values)
            values[:, hit] = self.depths[at[hit]].T
        chosen = values[_one_long(frequencies, self.shape[0], any_step=True)]
        return chosen[0] if _is_integer(frequencies) else chosen


def _is_integer(key: object) -> bool:
    return isinstance(key, (int, np.integer))


def _one_long(key: object, size: int, any_step: bool = False) -> slice:
    """An integer index as the slice of that one position (its axis kept), a slice with its bounds resolved."""
    if _is_integer(key):
        position = int(cast("int", key))
        if not -size <= position < size:
            raise IndexError(f"index {position} is out of bounds for an axis of size {size}")
        return slice(position % size, position % size + 1)
    if not isinstance(key, slice) or not (any_step or key.step in (None, 1)):
        raise IndexError(f"unwrapped depths take integers or unit-step slices for rows and columns, got {key!r}")
    start, stop, step = key.indices(size)
    if step < 0:  # indices() ends a slice down to the first position at -1, which a slice reads as the last
        return slice(start, None if stop < 0 else stop, step)
    return slice(start, max(start, stop), step)
