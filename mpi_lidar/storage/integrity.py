"""Integrity fingerprints: a chunk that was deleted, truncated or swapped is noticed where it is read.

Zarr reads a missing chunk file as the fill value, silently. So every chunk the project writes gets a
fingerprint, the SHA-256 of its *decoded* values (dtype, shape and C-order bytes), recorded with the chunk's
completion mark; readers recompute it chunk by chunk while streaming and raise :class:`IntegrityError`
naming the store, the array and the chunk. Hashing decoded values (not the compressed file) keeps the
fingerprint independent of the codec, so a store recompressed with the same values still verifies.

Guaranteed: a chunk whose values differ from what was written (deleted -> fill value, copied from another
chunk, overwritten) fails its fingerprint; a chunk whose file no longer decodes (truncated, garbled) fails
in its codec and is reported the same way. Every schema version the project writes (``mpi-lidar/<kind>@1``)
records fingerprints for every array (:func:`fingerprints_required`): a store of such a version without
them, without some array's, or with fingerprints of an array that is gone, is damaged
(:func:`recorded_fingerprints`), never read as data. Before any of a store's files is opened, every entry
under it must be a regular file or a directory (no links, devices or FIFOs) and its metadata files small
(:func:`check_store_files`); before any value is read or allocated, each array's declared chunk must be
within :data:`MAX_CHUNK_VALUES` and each chunk file no larger than its chunk's decoded bytes allow
(:func:`check_chunk_files`). Not guaranteed: a store whose fingerprints were rewritten together with its
data is not an integrity failure by this definition.
"""

from __future__ import annotations

import hashlib
import itertools
import os
import re
import stat
from collections.abc import Iterator, Mapping
from pathlib import Path

import numpy as np
import zarr
from numpy.typing import NDArray

from mpi_lidar.errors import StoreError
from mpi_lidar.threads import on_cores

FINGERPRINT_BYTES = 32
# A metadata file (zarr.json) larger than this is not read: a scan's, with the fingerprints of a 4-frequency
# 4096 x 4096 scan, takes about 20 kB.
MAX_METADATA_BYTES = 16 * 2**20
# Values one chunk may declare: 512 MiB of float32. A scan's maps come in chunks of 512 x 512; a dataset's rows
# of 4 frequencies in chunks of its largest chunk_rows (10,000,000) take 8 x 10**7. A chunk is decoded whole, so
# this bounds what one read allocates.
MAX_CHUNK_VALUES = 2**27
# What a chunk file may hold beyond its decoded bytes (codec headers; Blosc and Zstandard add tens of bytes).
CHUNK_FILE_SLACK_BYTES = 2**16
# Schemas of the project's stores: "mpi-lidar/<kind>@<version>"; every version so far records fingerprints.
SCHEMA = re.compile(r"mpi-lidar/(?P<kind>[a-z]+)@(?P<version>[0-9]+)")
FINGERPRINTS_SINCE_VERSION = 1
HEX_FINGERPRINT = re.compile(f"[0-9a-f]{{{2 * FINGERPRINT_BYTES}}}")


class IntegrityError(StoreError):
    """A chunk whose values are not those that were written, or that cannot be decoded."""


def fingerprints_required(schema: object) -> bool:
    """Whether a store of ``schema`` must record a fingerprint of every chunk of every array (every version of
    every store the project writes does: one without them is damaged, not old)."""
    found = SCHEMA.fullmatch(schema) if isinstance(schema, str) else None
    return found is not None and int(found["version"]) >= FINGERPRINTS_SINCE_VERSION


def check_store_files(path: str | Path) -> dict[str, int]:
    """Every file of a store (relative POSIX path -> size), after refusing what no reader may open.

    Called before zarr opens anything: an entry that is a symbolic link, a FIFO, a device or a socket (a
    chunk linked to ``/dev/zero`` would be read until memory runs out, a FIFO would hang), and a metadata
    file over :data:`MAX_METADATA_BYTES`, are an :class:`IntegrityError` naming them.
    """
    root = Path(path)
    files: dict[str, int] = {}
    pending = [root]
    while pending:
        folder = pending.pop()
        try:
            entries = list(os.scandir(folder))
        except OSError as exc:
            raise IntegrityError(f"{root}: cannot list {folder} ({exc.strerror or exc}); check its permissions "
                                 "or restore the store") from None
        for entry in entries:
            info = entry.stat(follow_symlinks=False)
            relative = Path(entry.path).relative_to(root).as_posix()
            if stat.S_ISDIR(info.st_mode):
                pending.append(Path(entry.path))
            elif not stat.S_ISREG(info.st_mode):
                what = "a symbolic link" if stat.S_ISLNK(info.st_mode) else "not a regular file"
                raise IntegrityError(f"{root}: {relative} is {what}; a store holds only its own files: replace it "
                                     "with the file itself or restore the store")
            else:
                if entry.name == "zarr.json" and info.st_size > MAX_METADATA_BYTES:
                    raise IntegrityError(f"{root}: {relative} takes {info.st_size:,} bytes, more than the "
                                         f"{MAX_METADATA_BYTES:,} a store's metadata may; the store is damaged: "
                                         "restore or regenerate it")
                files[relative] = info.st_size
    return files


def check_chunk_files(path: str | Path, files: Mapping[str, int], arrays: Mapping[str, zarr.Array]) -> None:
    """Refuse, before any value is read, an array whose declared chunk exceeds :data:`MAX_CHUNK_VALUES` or
    whose chunk files are larger than its chunk's decoded bytes (plus :data:`CHUNK_FILE_SLACK_BYTES`).

    ``files`` is :func:`check_store_files` of the store, ``arrays`` its arrays by name (their metadata only).
    """
    for name, array in arrays.items():
        chunk = tuple(array.shards or array.chunks)
        values = float(np.prod(chunk, dtype=np.float64))
        if values > MAX_CHUNK_VALUES:
            raise IntegrityError(f"{path}: array {name!r} declares chunks of {chunk}, more than the "
                                 f"{MAX_CHUNK_VALUES:,} values a chunk may hold; the store is damaged or not ours: "
                                 "restore or regenerate it")
        limit = values * np.dtype(array.dtype).itemsize + CHUNK_FILE_SLACK_BYTES
        prefix = f"{name}/"
        for relative, size in files.items():
            if relative.startswith(prefix) and not relative.endswith("zarr.json") and size > limit:
                raise IntegrityError(f"{path}: {relative} takes {size:,} bytes, more than a chunk of {name!r} "
                                     f"({chunk}, {array.dtype}) can; the store is damaged: restore or regenerate it")


def check_dimensions(path: str | Path, arrays: Mapping[str, zarr.Array], dims: Mapping[str, tuple[str, ...]],
                     max_values: float) -> dict[str, int]:
    """The size of every dimension, after checking the declared shapes (metadata only, nothing read).

    Each array named in ``dims`` must have as many axes as its dimensions, every dimension the same size in
    every array, and no array more than ``max_values`` values; anything else is an :class:`IntegrityError`
    naming the array (a store whose metadata declares 100000 x 100000 is refused before any allocation).
    """
    sizes: dict[str, int] = {}
    owner: dict[str, str] = {}
    for name, array in arrays.items():
        if name not in dims:
            continue
        shape = tuple(array.shape)
        if len(shape) != len(dims[name]):
            raise IntegrityError(f"{path}: array {name!r} has shape {shape}, not the dimensions {dims[name]}; the "
                                 "store is damaged: restore or regenerate it")
        if float(np.prod(shape, dtype=np.float64)) > max_values:
            raise IntegrityError(f"{path}: array {name!r} declares shape {shape}, more than the {max_values:,.0f} "
                                 "values it may hold; the store is damaged or not ours: restore or regenerate it")
        for dim, size in zip(dims[name], shape, strict=True):
            if sizes.setdefault(dim, size) != size:
                raise IntegrityError(f"{path}: array {name!r} has {size} along {dim!r} where {owner[dim]!r} has "
                                     f"{sizes[dim]}; the store is damaged: restore or regenerate it")
            owner.setdefault(dim, name)
    return sizes


def recorded_fingerprints(path: str | Path, recorded: object, arrays: Mapping[str, zarr.Array]
                          ) -> dict[str, list[str]]:
    """The fingerprints a store records (its ``chunk_sha256`` attribute), checked against its arrays.

    Every array must have a list of as many 64-digit hex fingerprints as it has chunks (counted from its
    metadata, before any list is built), and every recorded array must exist: a missing attribute, a missing
    entry, an entry for an array that is gone or a wrong count is an :class:`IntegrityError`.
    """
    if not isinstance(recorded, dict):
        raise IntegrityError(f"{path}: its chunk fingerprints (chunk_sha256) are missing or malformed; the store "
                             "is damaged: restore or regenerate it")
    gone = sorted(str(name) for name in set(recorded) - set(arrays))
    if gone:
        raise IntegrityError(f"{path}: array {gone[0]!r} is recorded in its fingerprints but gone from the store; "
                             "the store is damaged: restore or regenerate it")
    found: dict[str, list[str]] = {}
    for name, array in sorted(arrays.items()):
        expected = recorded.get(name)
        if expected is None:
            raise IntegrityError(f"{path}: array {name!r} has no recorded fingerprints; the store was altered: "
                                 "restore or regenerate it")
        if not (isinstance(expected, list) and len(expected) == array.nchunks
                and all(isinstance(h, str) and HEX_FINGERPRINT.fullmatch(h) for h in expected)):
            raise IntegrityError(f"{path}: the fingerprints of {name!r} are not one per chunk ({array.nchunks:,} "
                                 "chunks); the store is damaged: restore or regenerate it")
        found[name] = expected
    return found


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


def check_chunk_paths(array: zarr.Array, where: tuple[slice, ...], store: str) -> None:
    """Refuse, before they are read, the chunk files of a region that are not regular files or are larger than a
    chunk can be (one ``lstat`` each): a file replaced after the store was opened is caught where it is read.
    Stores other than a local directory are left to their own checks."""
    root = getattr(array.store, "root", None)
    if root is None:
        return
    chunks = tuple(array.shards or array.chunks)
    limit = float(np.prod(chunks, dtype=np.float64)) * np.dtype(array.dtype).itemsize + CHUNK_FILE_SLACK_BYTES
    where = (*where, *(slice(None),) * (len(array.shape) - len(where)))  # axes left out: whole
    boxes = [slice(*w.indices(n)[:2]) for w, n in zip(where, array.shape, strict=True)]
    spans = [range(w.start // c, -(-w.stop // c)) for w, c in zip(boxes, chunks, strict=True)]
    for cell in itertools.product(*spans):
        path = Path(root) / array.path / array.metadata.encode_chunk_key(cell)
        try:
            info = path.lstat()
        except OSError:  # absent: a fill value, which the fingerprint judges
            continue
        if not stat.S_ISREG(info.st_mode) or info.st_size > limit:
            what = "is not a regular file" if not stat.S_ISREG(info.st_mode) else f"takes {info.st_size:,} bytes"
            raise IntegrityError(f"{store}: {path.relative_to(root).as_posix()} {what}, which no chunk of "
                                 f"{array.path!r} can be; restore or regenerate the store")


def read_chunk(array: zarr.Array, where: tuple[slice, ...], store: str, name: str, index: object) -> NDArray:
    """One chunk's values; a chunk that no longer decodes is an :class:`IntegrityError` naming it, and a chunk
    file that is a link, a special file or larger than a chunk is refused before it is read."""
    check_chunk_paths(array, where, store)
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
    if expected is not None and len(expected) != array.nchunks:  # counted before a list of them is built
        raise IntegrityError(f"{store}: {name!r} records {len(expected)} chunk fingerprints for {array.nchunks} "
                             "chunks; the store is damaged: restore or regenerate it")
    return list(chunk_slices(array.shape, array.chunks))


def verified_chunks(array: zarr.Array, expected: list[str] | None, store: str, name: str
                    ) -> Iterator[tuple[tuple[slice, ...], NDArray]]:
    """(where, values) of every chunk of an array, each checked against its recorded fingerprint (``expected``
    None: only that it decodes); one chunk in memory at a time."""
    for k, (index, where) in enumerate(_chunk_cells(array, expected, store, name)):
        chunk = np.asarray(read_chunk(array, where, store, name, index), dtype=array.dtype)
        if expected is not None:
            check_fingerprint(chunk, expected[k], store, name, index)
        yield where, chunk
