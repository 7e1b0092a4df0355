"""A scan's map kept in its store and read a band of rows at a time (:class:`StoredMap`)."""

from __future__ import annotations

from collections.abc import Iterator

import numpy as np
import zarr
from numpy.typing import NDArray

# Values a stored map reads at once, a band of whole chunk rows at a time (:class:`StoredMap`): 32 MiB of
# float32.
BAND_VALUES = 2**23


class StoredMap:
    """A map of a scan store read from the store when indexed, so that a large scan is never in memory at once:
    ``depth``/``amplitude`` (F, H, W) (``row_axis`` 1) or ``ray_directions`` (H, W, 3) (``row_axis`` 0).

    Slicing reads what it selects; ``[:, ys, xs]`` (``[ys, xs]`` for row axis 0) with integer arrays picks
    pixels a band of rows at a time; ``np.asarray`` reads it all. Values come as ``dtype`` (the maps as
    float32, like :func:`validate` makes them). The store was checked against its fingerprints when opened.
    """

    def __init__(self, array: zarr.Array, row_axis: int, dtype: np.dtype | type | None = None):
        self.array, self.row_axis = array, row_axis
        self.shape: tuple[int, ...] = tuple(array.shape)
        self.ndim = len(self.shape)
        self.stored_dtype = np.dtype(array.dtype)
        self.dtype = np.dtype(dtype or array.dtype)
        self._cached: tuple[slice, NDArray] | None = None

    def __array__(self, dtype: np.dtype | None = None, copy: bool | None = None) -> NDArray:
        return np.asarray(self[...], dtype=dtype)

    def __getitem__(self, key: object) -> NDArray:
        key = key if isinstance(key, tuple) else (key,)
        if any(isinstance(k, np.ndarray) for k in key):
            return self._pixels(key)
        rows = key[self.row_axis] if len(key) > self.row_axis else slice(None)
        if Ellipsis in key or not isinstance(rows, slice) or rows.step not in (None, 1):
            return np.asarray(self.array[key], dtype=self.dtype)
        start, stop, _ = rows.indices(self.shape[self.row_axis])
        if stop - start > self._band_rows():  # more than a band: read as asked, nothing kept
            return np.asarray(self.array[key], dtype=self.dtype)
        band, values = self._band(start, max(start, stop))
        return values[(*key[:self.row_axis], slice(start - band.start, stop - band.start), *key[self.row_axis + 1:])]

    def _band(self, start: int, stop: int) -> tuple[slice, NDArray]:
        """The last band of whole chunk rows read, if it holds rows start:stop, else the one that does.

        Correction reads a scan in tiles of fewer rows than a chunk holds; without this each chunk would be
        decoded once per tile that touches it.
        """
        cached = self._cached
        if cached is not None and cached[0].start <= start and stop <= cached[0].stop:
            return cached
        step = self.array.chunks[self.row_axis]
        band = slice(start // step * step, min(-(-stop // step) * step, self.shape[self.row_axis]))
        self._cached = (band, np.asarray(self.array[(slice(None),) * self.row_axis + (band,)], dtype=self.dtype))
        return self._cached

    def _band_rows(self) -> int:
        """Rows of a band: whole chunk rows, about :data:`BAND_VALUES` values (at least one chunk row)."""
        step = self.array.chunks[self.row_axis]
        per_row = max(1, int(np.prod(self.shape, dtype=np.int64)) // max(self.shape[self.row_axis], 1))
        return max(1, BAND_VALUES // (per_row * step)) * step

    def row_bands(self) -> list[slice]:
        """Row ranges of one band each (whole chunk rows, about :data:`BAND_VALUES` values)."""
        height, rows = self.shape[self.row_axis], self._band_rows()
        return [slice(top, min(top + rows, height)) for top in range(0, height, rows)]

    def rows(self, rows: slice) -> NDArray:
        """The values of a range of rows, every other axis whole."""
        return self[(slice(None),) * self.row_axis + (rows,)]

    def c_order_parts(self) -> Iterator[NDArray]:
        """The values in parts whose bytes, one after the other, are those of the whole array in C order."""
        for leading in np.ndindex(*self.shape[:self.row_axis]):
            for rows in self.row_bands():  # whole chunks, read once: past the band kept for tiles
                yield np.asarray(self.array[(*leading, rows)], dtype=self.dtype)

    def _pixels(self, key: tuple) -> NDArray:
        """``[:, ys, xs]`` (row axis 1) or ``[ys, xs]`` (row axis 0): the values of pixels (..., n, ...)."""
        if len(key) != self.row_axis + 2 or any(k != slice(None) for k in key[:self.row_axis]):
            raise IndexError(f"a stored map picks pixels as [{':, ' * self.row_axis}rows, columns], got {key!r}")
        ys, xs = (np.asarray(k) for k in key[self.row_axis:])
        out = np.empty((*self.shape[:self.row_axis], ys.size, *self.shape[self.row_axis + 2:]), dtype=self.dtype)
        for rows in self.row_bands():
            chosen = np.flatnonzero((ys >= rows.start) & (ys < rows.stop))
            if chosen.size:
                values = self.rows(rows)
                if self.row_axis:
                    out[:, chosen] = values[:, ys[chosen] - rows.start, xs[chosen]]
                else:
                    out[chosen] = values[ys[chosen] - rows.start, xs[chosen]]
        return out

