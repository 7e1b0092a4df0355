"""A scan's map kept in its store and read a band of rows at a time (:class:`StoredMap`).

Every read is of whole chunks, each checked against its fingerprint as it is read (not only when the store
was opened): a chunk deleted or replaced while a large scan is corrected is an
:class:`~mpi_lidar.storage.integrity.IntegrityError`, never fill values.
"""

from __future__ import annotations

from collections.abc import Iterator

import numpy as np
import zarr
from numpy.typing import NDArray

from mpi_lidar.storage.integrity import check_chunk_paths, check_fingerprint

# Values a stored map reads at once, a band of whole chunk rows at a time (:class:`StoredMap`): 32 MiB of
# float32.
BAND_VALUES = 2**23


class StoredMap:
    """A map of a scan store read from the store when indexed, so that a large scan is never in memory at once:
    ``depth``/``amplitude`` (F, H, W) (``row_axis`` 1) or ``ray_directions`` (H, W, 3) (``row_axis`` 0).

    Slicing reads what it selects; ``[:, ys, xs]`` (``[ys, xs]`` for row axis 0) with integer arrays picks
    pixels a band of rows at a time; ``np.asarray`` reads it all. Values come as ``dtype`` (the maps as
    float32, like :func:`validate` makes them). ``fingerprints`` (one per chunk, C order of the chunk grid, as
    the store records them) check every chunk each time it is read; ``store`` and ``name`` name it in the error.
    """

    def __init__(self, array: zarr.Array, row_axis: int, dtype: np.dtype | type | None = None,
                 fingerprints: list[str] | None = None, store: str = "", name: str = ""):
        self.array, self.row_axis = array, row_axis
        self.fingerprints, self.store, self.name = fingerprints, store, name
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
            return self._read(tuple(slice(None) for _ in self.shape))[key]  # all of it, as np.asarray does
        start, stop, _ = rows.indices(self.shape[self.row_axis])
        if stop - start > self._band_rows():  # more than a band: read as asked, nothing kept
            return self._read(self._region(key))[self._within(key)]
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
        self._cached = (band, self._read((slice(None),) * self.row_axis + (band,)))
        return self._cached

    def _region(self, key: tuple) -> tuple[slice, ...]:
        """The box of ``key`` (integers and unit-step slices, axes left out taken whole) as slices per axis."""
        region = []
        for axis, size in enumerate(self.shape):
            k = key[axis] if axis < len(key) else slice(None)
            if isinstance(k, slice) and k.step in (None, 1):
                start, stop, _ = k.indices(size)
                region.append(slice(start, max(start, stop)))
            elif isinstance(k, (int, np.integer)) and -size <= k < size:
                region.append(slice(int(k) % size, int(k) % size + 1))
            else:
                region.append(slice(0, size))
        return tuple(region)

    def _within(self, key: tuple) -> tuple:
        """``key`` applied to the values of its box (:meth:`_region`): integers pick 0, slices take all."""
        within: list[object] = []
        for axis in range(len(self.shape)):
            k = key[axis] if axis < len(key) else slice(None)
            within.append(0 if isinstance(k, (int, np.integer)) else slice(None) if isinstance(k, slice)
                          and k.step in (None, 1) else k)
        return tuple(within)

    def _read(self, region: tuple[slice, ...]) -> NDArray:
        """The values of a box (unit-step slices per axis), read as whole chunks, each checked against its
        fingerprint, then cut to the box."""
        chunks = self.array.chunks
        region = (*region, *(slice(None),) * (len(self.shape) - len(region)))  # axes left out: whole
        region = tuple(slice(*r.indices(n)[:2]) for r, n in zip(region, self.shape, strict=True))
        aligned = tuple(slice(r.start // c * c, min(-(-r.stop // c) * c, n))
                        for r, c, n in zip(region, chunks, self.shape, strict=True))
        check_chunk_paths(self.array, aligned, self.store)
        values = np.asarray(self.array[aligned])
        if self.fingerprints is not None:
            grid = tuple(-(-n // c) for n, c in zip(self.shape, chunks, strict=True))
            for index in np.ndindex(*(-(-(a.stop - a.start) // c) for a, c in zip(aligned, chunks, strict=True))):
                cell = tuple(a.start // c + i for a, c, i in zip(aligned, chunks, index, strict=True))
                where = tuple(slice(i * c, i * c + c) for i, c in zip(index, chunks, strict=True))
                check_fingerprint(values[where], self.fingerprints[int(np.ravel_multi_index(cell, grid))],
                                  self.store, self.name, cell)
        cut = tuple(slice(r.start - a.start, r.stop - a.start) for r, a in zip(region, aligned, strict=True))
        return np.asarray(values[cut], dtype=self.dtype)

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
                box = (*(slice(i, i + 1) for i in leading), rows)  # the axes after the rows: whole
                first: tuple[int, ...] = (0,) * len(leading)
                yield self._read(box)[first]

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

