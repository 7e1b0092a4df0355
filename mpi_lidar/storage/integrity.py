"""Integrity fingerprints: a chunk that was deleted, truncated or swapped is noticed where it is read.

Zarr reads a missing chunk file as the fill value, silently. So every chunk the project writes gets a
fingerprint, the SHA-256 of its *decoded* values (dtype, shape and C-order bytes), recorded with the chunk's
completion mark; readers recompute it chunk by chunk while streaming and raise :class:`IntegrityError`
naming the store, the array and the chunk. Hashing decoded values (not the compressed file) keeps the
fingerprint independent of the codec, so a store recompressed with the same values still verifies.

Guaranteed: a chunk whose values differ from what was written (deleted -> fill value, copied from another
chunk, overwritten) fails its fingerprint; a chunk whose file no longer decodes (truncated, garbled) fails
in its codec and is reported the same way. Not guaranteed: stores written before fingerprints existed can
only be checked for readable chunks, and a store whose fingerprints were rewritten together with its data
is not an integrity failure by this definition.
"""

from __future__ import annotations

import hashlib
import itertools
from collections.abc import Iterator

import numpy as np
import zarr
from numpy.typing import NDArray

from mpi_lidar.errors import StoreError
from mpi_lidar.threads import on_cores

FINGERPRINT_BYTES = 32


class IntegrityError(StoreError):
    """A chunk whose values are not those that were written, or that cannot be decoded."""


def fingerprint(values: NDArray) -> bytes:
    """SHA-256 of an array's decoded values: dtype, shape, then its C-order bytes."""
    values = np.ascontiguousarray(values)
    digest = hashlib.sha256(f"{values.dtype.str}{values.shape}".encode())
    digest.update(values.reshape(-1).view(np.uint8).data)  # its C-order bytes, not copied
    return digest.digest()


def fingerprint_hex(values: NDArray) -> str:
    return fingerprint(values).hex()


def chunk_slices(shape: tuple[int, ...], chunks: tuple[int, ...]
                 ) -> Iterator[tuple[tuple[int, ...], tuple[slice, ...]]]:
    """Each chunk's grid index and its slices, in C order of the chunk grid."""
    grid = [range(-(-n // c)) for n, c in zip(shape, chunks, strict=True)]
    for index in itertools.product(*grid):
        yield index, tuple(slice(i * c, min((i + 1) * c, n)) for i, c, n in zip(index, chunks, shape, strict=True))


def array_fingerprints(values: NDArray, chunks: tuple[int, ...]) -> list[str]:
    """Hex fingerprints of every chunk of ``values`` cut by ``chunks``, in C order of the chunk grid."""
    return [fingerprint_hex(values[where]) for _, where in chunk_slices(values.shape, chunks)]


def read_chunk(array: zarr.Array, where: tuple[slice, ...], store: str, name: str, index: object) -> NDArray:
    """One chunk's values; a chunk that no longer decodes is an :class:`IntegrityError` naming it."""
    try:
        return np.asarray(array[where])
    except Exception as exc:  # codecs raise RuntimeError, ValueError or their own types on damaged bytes
        reason = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        raise IntegrityError(f"{store}: chunk {index} of {name!r} cannot be decoded ({reason}); the store is "
                             "damaged: restore or regenerate it") from None


def check_fingerprint(values: NDArray, expected: bytes | str, store: str, name: str, index: object) -> None:
    """Raise :class:`IntegrityError` unless ``values`` has the fingerprint recorded when it was written."""
    actual = fingerprint(values)
    expected_bytes = bytes.fromhex(expected) if isinstance(expected, str) else bytes(expected)
    if actual != expected_bytes:
        raise IntegrityError(f"{store}: chunk {index} of {name!r} does not hold the values written there "
                             "(deleted, truncated or replaced); restore or regenerate the store")


def verify_array(array: zarr.Array, expected: list[str] | None, store: str, name: str) -> NDArray:
    """Read a whole array, each chunk checked against its recorded fingerprint; the values.

    ``expected`` None (a store written before fingerprints) only checks that every chunk decodes. The array
    is decoded in one read (zarr decodes its chunks concurrently), then each chunk's values are checked (on
    every core; the error names the first damaged chunk in C order); a read that fails is done again chunk by
    chunk, which names the chunk that does not decode.
    """
    cells = _chunk_cells(array, expected, store, name)
    try:
        values = np.asarray(array[...], dtype=array.dtype)
    except Exception:  # codecs raise several types on damaged bytes
        values = np.empty(array.shape, dtype=array.dtype)
        for where, chunk in verified_chunks(array, expected, store, name):
            values[where] = chunk
        return values
    if expected is not None:
        on_cores(lambda k: check_fingerprint(values[cells[k][1]], expected[k], store, name, cells[k][0]),
                 range(len(cells)))
    return values


def _chunk_cells(array: zarr.Array, expected: list[str] | None, store: str, name: str
                 ) -> list[tuple[tuple[int, ...], tuple[slice, ...]]]:
    """The array's chunks (grid index, slices); as many as ``expected`` records, or an :class:`IntegrityError`."""
    cells = list(chunk_slices(array.shape, array.chunks))
    if expected is not None and len(expected) != len(cells):
        raise IntegrityError(f"{store}: {name!r} records {len(expected)} chunk fingerprints for {len(cells)} "
                             "chunks; the store is damaged: restore or regenerate it")
    return cells


def verified_chunks(array: zarr.Array, expected: list[str] | None, store: str, name: str
                    ) -> Iterator[tuple[tuple[slice, ...], NDArray]]:
    """(where, values) of every chunk of an array, each checked against its recorded fingerprint (``expected``
    None: only that it decodes); one chunk in memory at a time."""
    for k, (index, where) in enumerate(_chunk_cells(array, expected, store, name)):
        chunk = np.asarray(read_chunk(array, where, store, name, index), dtype=array.dtype)
        if expected is not None:
            check_fingerprint(chunk, expected[k], store, name, index)
        yield where, chunk
