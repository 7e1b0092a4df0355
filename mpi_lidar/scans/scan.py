"""Scans: depth and amplitude maps at several frequencies, the scanner geometry, and an optional reference.

Store (``*.scan.zarr``, Zarr v3, schema ``mpi-lidar/scan@1``): ``depth`` and ``amplitude`` float32
(F, H, W) [m, V^2] with dimensions (frequency, y, x), or raw ``taps`` (F, 4, H, W) [V^2] from which they are
demodulated; optional geometry: ``azimuth_rad`` (W,) and ``elevation_rad`` (H,) of the scan grid, or
``ray_directions`` (H, W, 3) unit vectors; optional ``reference_depth`` (H, W) [m] and ``reference_mask``
(H, W) bool for evaluation. Root attributes: ``schema``, ``frequencies_hz``, ``name``, free ``scene``
metadata and the chunk fingerprints ``chunk_sha256``.

For xarray (``xr.open_zarr``) the store also holds the coordinate ``frequency_hz`` (F,) [Hz] of the frequency
dimension and, where the scan has no azimuth (elevation) grid, the pixel indices ``x`` (``y``); ``azimuth_rad``
and ``elevation_rad`` are coordinates of the pixel columns and rows. Every array carries ``units`` and
``long_name``, and the metadata is consolidated. Readers take the frequencies from the root attributes, and
stores written without these coordinates read the same.

Geometry convention: the scanner sits at the origin; x right, y up, z forward. The ray of azimuth a and
elevation e is (cos e sin a, sin e, cos e cos a); depth is the range along the ray.
"""

from __future__ import annotations

import glob
import hashlib
import json
import warnings
import zipfile
from collections.abc import Callable, Iterator, Mapping, Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np
import zarr
from numpy.typing import NDArray

from mpi_lidar.constants import TABLE_SPEED_OF_LIGHT_M_PER_S
from mpi_lidar.errors import StoreError
from mpi_lidar.physics import demod
from mpi_lidar.storage.atomic import atomic_path
from mpi_lidar.storage.integrity import fingerprint_hex, verified_chunks, verify_array
from mpi_lidar.threads import on_cores

SCAN_SCHEMA = "mpi-lidar/scan@1"
SCAN_SUFFIX = ".scan.zarr"
# Every array of a scan together, decoded: depth and amplitude of 4 frequencies x 4096 x 4096 in float32 take
# half of it. Correction holds a few times this while it works, so more would not fit a worker safely.
MAX_SCAN_BYTES = 2**30
MAX_ARRAY_VALUES = 2**28  # 1 GiB of float32 per array: 4 taps x 4 frequencies x 4096 x 4096
# Values a stored map reads at once, a band of whole chunk rows at a time (:class:`StoredMap`): 32 MiB of
# float32.
BAND_VALUES = 2**23
# Correction keeps the depth and amplitude of a scan larger than this in its store (:class:`StoredMap`):
# 256 MiB of float32 maps, a 4-frequency scan of about 2900 x 2900.
STORED_MAPS_ABOVE_BYTES = 2**28


class ScanError(StoreError):
    """A scan that cannot be read or used."""


@dataclass(frozen=True)
class Scan:
    """One scan in memory. Arrays are validated by :func:`validate`."""

    name: str
    frequencies_hz: tuple[float, ...]
    depth: NDArray[np.float32]
    amplitude: NDArray[np.float32]
    azimuth_rad: NDArray[np.float64] | None = None
    elevation_rad: NDArray[np.float64] | None = None
    ray_directions: NDArray[np.float32] | None = None
    reference_depth: NDArray[np.float32] | None = None
    reference_mask: NDArray[np.bool_] | None = None
    taps: NDArray[np.float32] | None = None
    scene: dict[str, object] = field(default_factory=dict)

    @property
    def shape(self) -> tuple[int, int]:
        return self.depth.shape[1], self.depth.shape[2]

    @property
    def has_geometry(self) -> bool:
        return self.ray_directions is not None or (self.azimuth_rad is not None and self.elevation_rad is not None)

    def rays(self) -> NDArray[np.float64] | None:
        """Unit ray direction per pixel (H, W, 3), or None for a scan without geometry."""
        if self.ray_directions is not None:
            return np.asarray(self.ray_directions, dtype=np.float64)
        if self.azimuth_rad is None or self.elevation_rad is None:
            return None
        return grid_rays(self.azimuth_rad, self.elevation_rad)

    def ray_rows(self) -> RayRows | None:
        """The unit rays (H, W, 3) a band of rows at a time (``rays[rows]``), or None without geometry."""
        return RayRows(self) if self.has_geometry else None

    def pixel_rays(self, ys: NDArray, xs: NDArray) -> NDArray[np.float64]:
        """Unit rays (n, 3) of the pixels at rows ``ys`` and columns ``xs`` (n,), as :meth:`rays` gives them."""
        if self.ray_directions is not None:
            return np.asarray(self.ray_directions[ys, xs], dtype=np.float64)
        if self.azimuth_rad is None or self.elevation_rad is None:
            raise ValueError(f"scan {self.name} has no geometry")
        return grid_rays(np.asarray(self.azimuth_rad)[xs], np.asarray(self.elevation_rad)[ys], pairs=True)

    def raw_pixels(self) -> NDArray[np.float32]:
        """Per-pixel raw measurements (H*W, 2F) ordered like a dataset's features: depths, then amplitudes."""
        f = len(self.frequencies_hz)
        stacked = np.concatenate([np.asarray(self.depth).reshape(f, -1), np.asarray(self.amplitude).reshape(f, -1)],
                                 axis=0)
        return np.ascontiguousarray(stacked.T, dtype=np.float32)

    def in_memory(self) -> bool:
        """Whether the depth and amplitude maps are in memory, not read from the store (:class:`StoredMap`)."""
        return not isinstance(self.depth, StoredMap) and not isinstance(self.amplitude, StoredMap)

    def content_sha256(self) -> str:
        """Identity of what correction reads: frequencies, depth and amplitude maps, geometry."""
        digest = hashlib.sha256(json.dumps([float(f) for f in self.frequencies_hz]).encode())
        for array in (self.depth, self.amplitude, self.azimuth_rad, self.elevation_rad, self.ray_directions):
            parts = array.c_order_parts() if isinstance(array, StoredMap) else [] if array is None else [array]
            for part in parts:
                digest.update(memoryview(np.ascontiguousarray(part)).cast("B"))  # no copy of the bytes
        return digest.hexdigest()


def grid_rays(azimuth_rad: NDArray, elevation_rad: NDArray, pairs: bool = False) -> NDArray[np.float64]:
    """Unit rays (H, W, 3) of an azimuth (W,) by elevation (H,) scan grid; with ``pairs``, the rays (n, 3) of
    n (azimuth, elevation) pairs."""
    az = np.asarray(azimuth_rad, dtype=np.float64)
    el = np.asarray(elevation_rad, dtype=np.float64)
    if not pairs:
        az, el = az[None, :], el[:, None]
    return np.stack([np.cos(el) * np.sin(az), np.sin(el) * np.ones_like(az), np.cos(el) * np.cos(az)], axis=-1)


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


class RayRows:
    """A scan's unit rays (H, W, 3), built for a band of rows when sliced (``rays[top:bottom]``): a large
    scan never holds all of them in float64 at once. Each row is exactly that row of :meth:`Scan.rays`."""

    def __init__(self, scan: Scan):
        self.scan = scan
        self.shape = (*scan.shape, 3)

    def __getitem__(self, rows: slice) -> NDArray[np.float64]:
        if self.scan.ray_directions is not None:
            return np.asarray(self.scan.ray_directions[rows], dtype=np.float64)
        return grid_rays(self.scan.azimuth_rad, np.asarray(self.scan.elevation_rad)[rows])


def validate(scan: Scan, source: str) -> Scan:
    """Check shapes, dtypes and values; return the scan with float32 maps. One clear error per problem."""
    f = len(scan.frequencies_hz)
    if f == 0 or any(not np.isfinite(x) or x <= 0 for x in scan.frequencies_hz):
        raise ScanError(f"{source}: frequencies_hz must be positive numbers, got {list(scan.frequencies_hz)}")
    if len(set(scan.frequencies_hz)) != f:
        raise ScanError(f"{source}: frequencies_hz has duplicates {list(scan.frequencies_hz)}; each frequency "
                        "is measured once")
    stored = isinstance(scan.depth, StoredMap) and isinstance(scan.amplitude, StoredMap)
    depth, amplitude = (scan.depth, scan.amplitude) if stored else (np.asarray(scan.depth), np.asarray(scan.amplitude))
    if depth.ndim != 3 or depth.shape[0] != f:
        raise ScanError(f"{source}: depth must have shape (F={f}, H, W), got {depth.shape}")
    if amplitude.shape != depth.shape:
        raise ScanError(f"{source}: amplitude shape {amplitude.shape} differs from depth shape {depth.shape}")
    for name, array in (("depth", depth), ("amplitude", amplitude)):
        dtype = array.stored_dtype if stored else array.dtype
        if not np.issubdtype(dtype, np.floating):
            raise ScanError(f"{source}: {name} must be floating point, got {dtype}")
    negative = sum(int((part < 0).sum()) for part in _parts(amplitude))
    if negative:
        raise ScanError(f"{source}: amplitude has negative values ({negative} pixels); an "
                        "amplitude is a magnitude: check the importer or the tap order")
    if not any(np.isfinite(part).any() for part in _parts(depth)):
        raise ScanError(f"{source}: no pixel has a finite depth")
    h, w = depth.shape[1:]
    _check_optional(source, "azimuth_rad", scan.azimuth_rad, (w,))
    _check_optional(source, "elevation_rad", scan.elevation_rad, (h,))
    _check_optional(source, "ray_directions", scan.ray_directions, (h, w, 3))
    _check_optional(source, "reference_depth", scan.reference_depth, (h, w))
    _check_optional(source, "reference_mask", scan.reference_mask, (h, w))
    _check_optional(source, "taps", scan.taps, (f, 4, h, w))
    if scan.reference_mask is not None and np.asarray(scan.reference_mask).dtype != np.bool_:
        raise ScanError(f"{source}: reference_mask must be boolean, got {np.asarray(scan.reference_mask).dtype}; "
                        "store it as bool (True where the reference holds)")
    for name in ("azimuth_rad", "elevation_rad", "ray_directions", "reference_depth", "taps"):
        value = getattr(scan, name)
        if value is None:
            continue
        dtype = value.stored_dtype if isinstance(value, StoredMap) else np.asarray(value).dtype
        if not np.issubdtype(dtype, np.floating):
            raise ScanError(f"{source}: {name} must be floating point, got {dtype}")
    if stored:
        return scan
    return replace(scan, depth=depth.astype(np.float32, copy=False), amplitude=amplitude.astype(np.float32, copy=False))


def _parts(values: NDArray | StoredMap) -> Iterator[NDArray]:
    """An array whole, or a stored map a band of rows at a time."""
    if isinstance(values, StoredMap):
        yield from values.c_order_parts()
    else:
        yield values


def _check_optional(source: str, name: str, array: NDArray | None, shape: tuple[int, ...]) -> None:
    if array is not None and np.shape(array) != shape:
        raise ScanError(f"{source}: {name} must have shape {shape}, got {np.shape(array)}")


def from_taps(name: str, frequencies_hz: tuple[float, ...], taps: NDArray, c: float, **optional: object) -> Scan:
    """A scan from raw taps (F, 4, H, W), demodulated with eq 5-7 (float64 differencing)."""
    taps = np.asarray(taps)
    if taps.ndim != 4 or taps.shape[:2] != (len(frequencies_hz), 4) or not np.issubdtype(taps.dtype, np.floating):
        raise ScanError(f"{name}: taps must be floating point of shape (F={len(frequencies_hz)}, 4, H, W), got "
                        f"{taps.dtype}{taps.shape}")
    moved = np.moveaxis(taps, 1, -1)  # (F, H, W, 4)
    freqs = np.asarray(frequencies_hz)[:, None, None]
    depth, amplitude = demod.depth_and_amplitude(moved, freqs, c)
    return Scan(name=name, frequencies_hz=tuple(frequencies_hz), depth=depth.astype(np.float32),
                amplitude=amplitude.astype(np.float32), taps=taps.astype(np.float32), **optional)


# --- the store --------------------------------------------------------------------------------------------

OPTIONAL_ARRAYS = {
    "azimuth_rad": ("x",), "elevation_rad": ("y",), "ray_directions": ("y", "x", "xyz"),
    "reference_depth": ("y", "x"), "reference_mask": ("y", "x"), "taps": ("frequency", "tap", "y", "x"),
}
# Arrays written for xarray only (see the module docstring); no reader takes data from them.
COORDINATE_ARRAYS = ("frequency_hz", "y", "x")
# units (UDUNITS) and long_name of every array a scan or corrected store may hold
ARRAY_METADATA: dict[str, tuple[str, str]] = {
    "depth": ("m", "measured range along the ray"),
    "amplitude": ("V^2", "measured amplitude"),
    "taps": ("V^2", "demodulation taps"),
    "azimuth_rad": ("rad", "azimuth of the pixel column"),
    "elevation_rad": ("rad", "elevation of the pixel row"),
    "ray_directions": ("1", "unit ray direction (x right, y up, z forward)"),
    "reference_depth": ("m", "reference range along the ray"),
    "reference_mask": ("1", "reference region mask (1 where the reference holds)"),
    "frequency_hz": ("Hz", "modulation frequency"),
    "y": ("1", "pixel row"),
    "x": ("1", "pixel column"),
}


def write_scan(scan: Scan, path: str | Path, overwrite: bool = False) -> Path:
    """Write a scan store atomically (built beside ``path``, then renamed). Refuses to overwrite by default."""
    path = Path(path)
    scan = validate(scan, str(path))
    if path.exists() and not overwrite:
        raise ScanError(f"{path} already exists; choose another name or remove it")
    with atomic_path(path, replace=overwrite, what="scan", error=ScanError) as staging:
        group = zarr.open_group(store=str(staging), mode="w-")
        h, w = scan.shape
        maps = {name: (getattr(scan, name), ("frequency", "y", "x")) for name in ("depth", "amplitude")}
        optional = {name: (np.asarray(getattr(scan, name)), dims) for name, dims in OPTIONAL_ARRAYS.items()
                    if getattr(scan, name) is not None}
        write_described_arrays(group, {**maps, **optional}, scan.shape, scan.frequencies_hz,
                               chunks=dict.fromkeys(maps, (1, min(h, 512), min(w, 512))))
        group.attrs.update({"schema": SCAN_SCHEMA, "frequencies_hz": [float(f) for f in scan.frequencies_hz],
                            "name": scan.name, "scene": scan.scene, "chunk_sha256": store_fingerprints(group)})
        consolidate(staging)
    return path


def write_described_arrays(group: zarr.Group, arrays: Mapping[str, tuple[NDArray, tuple[str, ...]]],
                           shape: tuple[int, int], frequencies_hz: Sequence[float] | None = None,
                           metadata: Mapping[str, tuple[str, str]] | None = None,
                           chunks: Mapping[str, tuple[int, ...]] | None = None,
                           attributes: Mapping[str, Mapping[str, object]] | None = None) -> None:
    """Write data arrays (name -> (values, dimension names)) so that xarray reads the store: with coordinate
    arrays, and ``units``, ``long_name`` and ``coordinates`` on every array.

    Adds ``frequency_hz`` (with ``frequencies_hz`` given) and the pixel indices ``y``/``x`` of a grid without
    ``elevation_rad``/``azimuth_rad``. Each array is described from :data:`ARRAY_METADATA` and ``metadata``
    (name -> (units, long_name)), plus its own ``attributes``, in the one metadata write that creates it;
    ``chunks`` where an array's chunks are not zarr's own choice. Write the fingerprints after it.
    """
    h, w = shape
    planned = dict(arrays)
    if frequencies_hz is not None:
        planned["frequency_hz"] = (np.asarray(frequencies_hz, dtype=np.float64), ("frequency",))
    for index, grid, size in (("y", "elevation_rad", h), ("x", "azimuth_rad", w)):
        if grid not in planned:
            planned[index] = (np.arange(size, dtype=np.int64), (index,))
    described = {**ARRAY_METADATA, **(metadata or {})}
    coordinates = [name for name in ("frequency_hz", "elevation_rad", "azimuth_rad") if name in planned]
    for name, (values, dims) in planned.items():
        units, long_name = described.get(name, ("1", name.replace("_", " ")))
        attrs: dict[str, object] = {"units": units, "long_name": long_name, **(attributes or {}).get(name, {})}
        if name not in coordinates and name not in dims:
            own = " ".join(c for c in coordinates if set(planned[c][1]) <= set(dims))
            if own:
                attrs["coordinates"] = own
        extra = {"chunks": chunks[name]} if chunks and name in chunks else {}
        group.create_array(name, data=values, dimension_names=dims, attributes=attrs, **extra)


def consolidate(path: str | Path) -> None:
    """Consolidate a store's metadata (for xarray), once its attributes are final.

    Zarr warns that consolidated metadata is not (yet) part of the Zarr v3 specification; xarray and
    zarr-python read it, and the readers of this package read each array's own metadata.
    """
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message="Consolidated metadata", category=UserWarning)
        zarr.consolidate_metadata(str(path))


def store_fingerprints(group: zarr.Group) -> dict[str, list[str]]:
    """Fingerprints of every chunk of every array of a store just written (read back, so exactly as stored),
    one chunk of an array in memory at a time, an array per core."""
    arrays = dict(group.arrays())  # opened together: one round trip to the store, not one per array
    names = sorted(arrays)
    found = on_cores(lambda name: [fingerprint_hex(chunk) for _, chunk in verified_chunks(arrays[name], None,
                                                                                         str(group.store), name)],
                     names)  # an array per core: a chunk of each in memory at a time
    return dict(zip(names, found, strict=True))


def read_scan(path: str | Path, c: float = TABLE_SPEED_OF_LIGHT_M_PER_S, stored_above_bytes: float = float("inf")
              ) -> Scan:
    """Read and validate a scan store; depth/amplitude are demodulated from taps when only taps are stored.

    A store whose depth and amplitude (and ray directions) take more than ``stored_above_bytes`` as float32
    keeps them in the store: they come as :class:`StoredMap`, every chunk checked against its fingerprint
    here (one chunk at a time) and read again where correction needs it, a band of rows at a time.
    """
    path = Path(path)
    if not path.exists():
        raise ScanError(f"scan {path} does not exist")
    try:
        # Each array's own metadata, not the consolidated copy: that is what the chunks were written with.
        group = zarr.open_group(store=str(path), mode="r", use_consolidated=False)
        attrs = dict(group.attrs)
        arrays = dict(group.arrays())  # opened together: one round trip to the store, not one per array
        members = set(arrays)
    except Exception as exc:  # zarr raises several types for foreign or broken metadata
        raise ScanError(f"{path} is not a readable Zarr store ({type(exc).__name__})") from None
    if attrs.get("schema") != SCAN_SCHEMA:
        raise ScanError(f"{path} is not an mpi-lidar scan (schema {attrs.get('schema')!r}, expected {SCAN_SCHEMA!r})")
    try:
        _check_declared_sizes(path, arrays)
        frequencies = tuple(float(f) for f in attrs["frequencies_hz"])
        fingerprints = attrs.get("chunk_sha256")  # absent in scans written before fingerprints existed
        fingerprints = fingerprints if isinstance(fingerprints, dict) else {}

        maps = {"depth": 1, "amplitude": 1, "ray_directions": 0}
        in_store = {"depth", "amplitude"} <= members and stored_above_bytes < 4 * sum(
            np.prod(arrays[name].shape, dtype=np.float64) for name in maps if name in members)

        def read(name: str) -> NDArray | StoredMap:
            if in_store and name in maps:
                for _ in verified_chunks(arrays[name], fingerprints.get(name), str(path), name):
                    pass
                # The maps come as float32 (as validate makes them), ray directions as stored.
                return StoredMap(arrays[name], maps[name], None if name == "ray_directions" else np.float32)
            return verify_array(arrays[name], fingerprints.get(name), str(path), name)

        optional = {name: read(name) for name in OPTIONAL_ARRAYS if name in members}
        coordinates = {name: read(name) for name in COORDINATE_ARRAYS if name in members}
        if "frequency_hz" in coordinates and not np.array_equal(coordinates["frequency_hz"], frequencies):
            raise ScanError(f"{path}: its frequency_hz array {coordinates['frequency_hz'].tolist()} differs from "
                            f"its frequencies_hz attribute {list(frequencies)}; the store was altered")
        name = str(attrs.get("name") or path.name.removesuffix(SCAN_SUFFIX))
        scene = attrs.get("scene") or {}
        if {"depth", "amplitude"} <= members:
            scan = Scan(name=name, frequencies_hz=frequencies, depth=read("depth"), amplitude=read("amplitude"),
                        scene=scene, **optional)
        elif "taps" in members:
            taps = optional.pop("taps")
            scan = from_taps(name, frequencies, taps, c, scene=scene, **optional)
        else:
            raise ScanError(f"{path} has neither depth+amplitude nor taps; it is truncated or not a scan")
    except StoreError:  # ScanError and IntegrityError: already one clear line
        raise
    except (KeyError, ValueError, TypeError, OSError, RuntimeError) as exc:  # codecs raise RuntimeError
        reason = str(exc).splitlines()[0] if str(exc) else ""
        raise ScanError(f"{path} is damaged or truncated ({type(exc).__name__}: {reason})") from None
    return validate(scan, str(path))


def _check_declared_sizes(path: Path, arrays: Mapping[str, zarr.Array]) -> None:
    """Refuse a store whose declared arrays exceed the memory budget, before allocating anything.

    A damaged or hostile store can declare 4 x 8000 x 8000 pixels in a few hundred bytes of metadata.
    """
    check_memory_budget(path, [(f"array {name!r}", array.shape, array.dtype) for name, array in arrays.items()])


def check_memory_budget(path: Path, declared: list[tuple[str, tuple[int, ...], np.dtype]]) -> None:
    """Refuse what a scan's arrays declare, (what, shape, dtype) each, beyond one array's or the scan's budget.

    Called with the declared shapes only (store metadata, .npy headers, NetCDF variables), before any value
    is read or allocated.
    """
    total = 0.0
    for what, shape, dtype in declared:
        values = float(np.prod(shape, dtype=np.float64))
        if values > MAX_ARRAY_VALUES:
            raise ScanError(f"{path}: {what} declares shape {tuple(shape)}, more than the {MAX_ARRAY_VALUES:,} "
                            "values a scan array may hold; split the scan into smaller ones")
        total += values * np.dtype(dtype).itemsize
    if total > MAX_SCAN_BYTES:
        raise ScanError(f"{path}: its arrays declare {total / 2**30:.1f} GiB, more than the "
                        f"{MAX_SCAN_BYTES / 2**30:g} GiB a scan may hold in memory; split the scan into smaller ones")


def import_arrays(
    name: str, frequencies_hz: tuple[float, ...], arrays: dict[str, NDArray], c: float = TABLE_SPEED_OF_LIGHT_M_PER_S,
    source: str | None = None,
) -> Scan:
    """A scan from plain arrays (e.g. an ``.npz`` from another tool): depth+amplitude or taps, plus extras.

    ``source`` (default ``name``) names where the arrays come from in the error messages, e.g. the file.
    """
    source = source or name
    known = {"depth", "amplitude", *OPTIONAL_ARRAYS}
    unknown = sorted(set(arrays) - known - {"frequencies_hz"})
    if unknown:
        raise ScanError(f"{source}: unknown arrays {unknown}; expected some of {sorted(known)}")
    optional = {k: np.asarray(v) for k, v in arrays.items() if k in OPTIONAL_ARRAYS and k != "taps"}
    if "reference_mask" in optional:
        optional["reference_mask"] = _boolean_mask(source, optional["reference_mask"])
    if "depth" in arrays and "amplitude" in arrays:
        scan = Scan(name=name, frequencies_hz=tuple(frequencies_hz), depth=np.asarray(arrays["depth"]),
                    amplitude=np.asarray(arrays["amplitude"]), taps=arrays.get("taps"), **optional)
    elif "taps" in arrays:
        try:
            scan = from_taps(name, tuple(frequencies_hz), np.asarray(arrays["taps"]), c, **optional)
        except ScanError as exc:
            raise ScanError(f"{source}: {str(exc).removeprefix(f'{name}: ')}") from None
    else:
        raise ScanError(f"{source}: needs arrays 'depth' and 'amplitude' (F, H, W), or 'taps' (F, 4, H, W)")
    return validate(scan, source)


def _boolean_mask(name: str, mask: NDArray) -> NDArray[np.bool_]:
    """A 0/1 mask of any numeric type as booleans; anything else is refused rather than guessed."""
    if mask.dtype != np.bool_ and not (np.issubdtype(mask.dtype, np.number) and np.isin(mask, (0, 1)).all()):
        raise ScanError(f"{name}: reference_mask must be boolean or 0/1, got {mask.dtype} with other values")
    return mask.astype(bool)


def load_npz(path: str | Path, frequencies_hz: tuple[float, ...] | None = None,
             variables: Mapping[str, str] | None = None) -> Scan:
    """Import an ``.npz`` archive (arrays named as in the scan store; frequencies_hz inside or given).

    ``variables`` maps scan array names to the archive's member names (``{"depth": "range_m"}``); members
    it does not name must be named as in the scan store. Every member's header is checked (dtype, declared
    size against the memory budget) before any array is read, so a damaged or hostile archive is refused
    without allocating what it claims.
    """
    path = Path(path)
    variables = check_variables(variables)
    _check_npz_headers(path)
    try:
        with np.load(path, allow_pickle=False) as archive:
            arrays = {key: archive[key] for key in archive.files}
    except Exception as exc:  # zipfile, numpy and OS errors of a damaged archive
        raise ScanError(f"{path} is not a readable .npz archive ({type(exc).__name__}: {exc})") from None
    arrays = _renamed(path, arrays, variables)
    stored = arrays.pop("frequencies_hz", None)
    if frequencies_hz is None and stored is None:
        raise ScanError(f"{path} holds no frequencies_hz array; pass --frequencies")
    freqs = frequencies_hz if frequencies_hz is not None else _stored_frequencies(path, stored)
    return import_arrays(path.name.removesuffix(".npz"), tuple(float(f) for f in freqs), arrays, source=str(path))


def _stored_frequencies(path: Path, stored: NDArray) -> NDArray:
    if stored.ndim != 1 or stored.size == 0 or not np.issubdtype(stored.dtype, np.number):
        raise ScanError(f"{path}: frequencies_hz must be a 1-D array of numbers in Hz, got "
                        f"{stored.dtype}{stored.shape}; pass --frequencies instead")
    return stored


def _check_npz_headers(path: Path) -> None:
    """Refuse members that are not plain numeric arrays, or that declare more than a scan may hold."""
    try:
        with zipfile.ZipFile(path) as archive:
            declared = []
            for info in archive.infolist():
                with archive.open(info) as member:
                    version = np.lib.format.read_magic(member)
                    read_header = (np.lib.format.read_array_header_1_0 if version == (1, 0)
                                   else np.lib.format.read_array_header_2_0)
                    shape, _, dtype = read_header(member)
                if dtype.hasobject or dtype.kind not in "biuf":
                    raise ScanError(f"{path}: member {info.filename} has dtype {dtype}; only numbers and booleans "
                                    "can be imported")
                declared.append((f"member {info.filename}", shape, dtype))
    except ScanError:
        raise
    except Exception as exc:  # not a zip, a member without an .npy header, a damaged header
        raise ScanError(f"{path} is not a readable .npz archive ({type(exc).__name__}: {exc})") from None
    check_memory_budget(path, declared)


# --- NetCDF / HDF5, and many files at once ----------------------------------------------------------------

IMPORT_SUFFIXES = (".npz", ".nc", ".h5", ".hdf5")
# The names a file's variables can be mapped to (``--var NAME=VARIABLE``).
SCAN_VARIABLES = ("depth", "amplitude", *OPTIONAL_ARRAYS, "frequencies_hz")
# Units a NetCDF/HDF5 variable may declare (its ``units`` attribute), as factors to the store's unit; a
# variable without ``units`` is taken to be in the store's unit already.
_METRES = {"m": 1.0, "meter": 1.0, "meters": 1.0, "metre": 1.0, "metres": 1.0, "cm": 1e-2, "mm": 1e-3, "km": 1e3}
_RADIANS = {"rad": 1.0, "radian": 1.0, "radians": 1.0, "deg": np.pi / 180, "degree": np.pi / 180,
            "degrees": np.pi / 180}
_HERTZ = {"hz": 1.0, "khz": 1e3, "mhz": 1e6, "ghz": 1e9}
UNITS = {"depth": ("m", _METRES), "reference_depth": ("m", _METRES), "azimuth_rad": ("rad", _RADIANS),
         "elevation_rad": ("rad", _RADIANS), "frequencies_hz": ("Hz", _HERTZ)}
_HDF5_MAGIC = b"\x89HDF\r\n\x1a\n"
_NETCDF3_MAGIC = b"CDF"


def check_variables(variables: Mapping[str, str] | None) -> dict[str, str]:
    """A mapping of scan array names to a file's variable names, checked: known names, one variable each."""
    variables = dict(variables or {})
    unknown = sorted(set(variables) - set(SCAN_VARIABLES))
    if unknown:
        raise ScanError(f"--var names {unknown}, which are not scan arrays; map some of {list(SCAN_VARIABLES)}")
    shared = sorted({v for v in variables.values() if list(variables.values()).count(v) > 1})
    if shared:
        raise ScanError(f"--var maps several scan arrays to the variable(s) {shared}; map each variable once")
    return variables


def _renamed(path: Path, arrays: dict[str, NDArray], variables: Mapping[str, str]) -> dict[str, NDArray]:
    missing = sorted(f"{name}={member}" for name, member in variables.items() if member not in arrays)
    if missing:
        raise ScanError(f"{path} has no array for --var {', '.join(missing)}; it holds {sorted(arrays)}")
    rest = {key: value for key, value in arrays.items() if key not in set(variables.values())}
    clash = sorted(set(rest) & set(variables))
    if clash:
        raise ScanError(f"{path} holds {clash} itself and --var maps other arrays to them; remove one or the other")
    return {**rest, **{name: arrays[member] for name, member in variables.items()}}


def load_netcdf(path: str | Path, frequencies_hz: tuple[float, ...] | None = None,
                variables: Mapping[str, str] | None = None) -> Scan:
    """Import a NetCDF (3 or 4) or HDF5 file through xarray: its variables named as in the scan store, or
    mapped by ``variables`` (``{"depth": "range_m", "amplitude": "intensity"}``); other variables are ignored.

    The frequencies come from ``frequencies_hz``, else the variable ``frequencies_hz`` (or ``frequency_hz``),
    else the global attribute ``frequencies_hz``. CF decoding applies (``_FillValue`` becomes NaN,
    ``scale_factor``), and a ``units`` attribute is converted (mm, cm or km to m, degrees to rad, kHz, MHz
    or GHz to Hz; other units are refused). Each variable's dtype and declared size are checked against the
    memory budget before anything is read.
    """
    import xarray as xr

    path = Path(path)
    variables = check_variables(variables)
    engine, options = _netcdf_engine(path)
    try:
        ds = xr.open_dataset(path, engine=engine, decode_times=False, decode_timedelta=False, cache=False,
                             **options)
    except Exception as exc:  # h5netcdf, h5py and scipy raise many types for foreign or damaged files
        raise ScanError(f"{path} is not a readable NetCDF/HDF5 file ({_reason(exc)})") from None
    with ds:
        missing = sorted(f"{name}={v}" for name, v in variables.items() if v not in ds.variables)
        if missing:
            raise ScanError(f"{path} has no variable for --var {', '.join(missing)}; it holds "
                            f"{sorted(map(str, ds.variables))}")
        chosen = {name: variables.get(name, name) for name in SCAN_VARIABLES
                  if variables.get(name, name) in ds.variables}
        if "frequencies_hz" not in chosen and "frequency_hz" in ds.variables:
            chosen["frequencies_hz"] = "frequency_hz"
        _check_variable_sizes(path, ds, chosen)
        try:
            arrays = {name: _in_store_units(path, name, ds[v].attrs.get("units"), ds[v].values)
                      for name, v in chosen.items()}
        except ScanError:
            raise
        except Exception as exc:  # a damaged chunk or a failing filter while reading
            raise ScanError(f"{path} cannot be read ({_reason(exc)})") from None
        stored = arrays.pop("frequencies_hz", None)
        if stored is None and "frequencies_hz" in ds.attrs:
            stored = np.atleast_1d(np.asarray(ds.attrs["frequencies_hz"]))
    if frequencies_hz is None and stored is None:
        raise ScanError(f"{path} holds no frequencies_hz variable or attribute; pass --frequencies")
    freqs = frequencies_hz if frequencies_hz is not None else _stored_frequencies(path, stored)
    return import_arrays(path.stem, tuple(float(f) for f in freqs), arrays, source=str(path))


def _reason(exc: Exception) -> str:
    text = str(exc).strip().splitlines()
    return f"{type(exc).__name__}: {text[0]}" if text else type(exc).__name__


def _netcdf_engine(path: Path) -> tuple[str, dict[str, object]]:
    """xarray's engine for the file, from its first bytes: h5netcdf for NetCDF-4/HDF5, scipy for NetCDF-3."""
    try:
        with path.open("rb") as stream:
            magic = stream.read(len(_HDF5_MAGIC))
    except OSError as exc:
        raise ScanError(f"cannot read {path}: {exc.strerror or exc}") from None
    if magic == _HDF5_MAGIC:
        return "h5netcdf", {"phony_dims": "access"}  # plain HDF5 datasets have no dimension names
    if magic.startswith(_NETCDF3_MAGIC):
        return "scipy", {}
    raise ScanError(f"{path} is neither NetCDF nor HDF5 (it does not start with their signature)")


def _check_variable_sizes(path: Path, ds: object, chosen: Mapping[str, str]) -> None:
    """Numbers and booleans only, within the memory budget of a scan, before any variable is read."""
    for name, variable in chosen.items():
        if ds[variable].dtype.kind not in "biuf":
            raise ScanError(f"{path}: variable {variable!r} ({name}) has dtype {ds[variable].dtype}; only numbers "
                            "and booleans can be imported")
    check_memory_budget(path, [(f"variable {v!r}", ds[v].shape, ds[v].dtype) for v in chosen.values()])


def _in_store_units(path: Path, name: str, units: object, values: NDArray) -> NDArray:
    """``values`` converted from their declared ``units`` to the unit of the scan store (see :data:`UNITS`)."""
    if name not in UNITS or units is None:
        return values
    unit, factors = UNITS[name]
    factor = factors.get(str(units).strip().lower())
    if factor is None:
        raise ScanError(f"{path}: {name} has units {units!r}; give it in {unit} or one of "
                        f"{', '.join(sorted(factors))}")
    return values if factor == 1.0 else values * factor


def load_scan_file(path: str | Path, frequencies_hz: tuple[float, ...] | None = None,
                   variables: Mapping[str, str] | None = None) -> Scan:
    """Import one file by its suffix: ``.npz`` (:func:`load_npz`), ``.nc``/``.h5``/``.hdf5`` (:func:`load_netcdf`)."""
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix == ".npz":
        return load_npz(path, frequencies_hz, variables)
    if suffix in IMPORT_SUFFIXES:
        return load_netcdf(path, frequencies_hz, variables)
    raise ScanError(f"{path}: cannot import {suffix or 'a file without suffix'}; give {', '.join(IMPORT_SUFFIXES)}")


def find_scan_files(sources: Sequence[str | Path]) -> list[Path]:
    """The files named directly, found in a directory (not recursively) or matched by a glob, in order, once.

    A source that names nothing importable is an error, so a mistyped path or pattern is never silently empty.
    """
    found: list[Path] = []
    for source in sources:
        path = Path(source)
        if path.is_dir():
            matches = sorted(p for p in path.iterdir() if _importable(p))
        elif path.exists():
            matches = [path]
        elif glob.has_magic(str(source)):
            matches = sorted(p for p in map(Path, glob.glob(str(source))) if _importable(p))
        else:
            raise ScanError(f"{source} does not exist")
        if not matches:
            raise ScanError(f"{source} holds or matches no {', '.join(IMPORT_SUFFIXES)} file")
        found += matches
    unique: dict[Path, Path] = {}
    for path in found:
        unique.setdefault(path.resolve(), path)
    return list(unique.values())


def _importable(path: Path) -> bool:
    return path.is_file() and path.suffix.lower() in IMPORT_SUFFIXES and not path.name.startswith(".")


def plan_import(files: Sequence[Path], out: str | Path) -> list[tuple[Path, Path]]:
    """(source, store) pairs: ``out`` itself for one file and an ``out`` ending in ``.scan.zarr``, else
    ``out/<stem>.scan.zarr`` per file. Two files for one store, or a store that exists, are refused."""
    out = Path(out)
    if out.name.endswith(SCAN_SUFFIX):
        if len(files) != 1:
            raise ScanError(f"--out {out} is one scan store, but {len(files)} files were given; give a directory "
                            f"as --out to write <dir>/<name>{SCAN_SUFFIX} for each")
        plan = [(Path(files[0]), out)]
    else:
        if out.exists() and not out.is_dir():
            raise ScanError(f"--out {out} exists and is not a directory")
        plan = [(Path(f), out / f"{Path(f).stem}{SCAN_SUFFIX}") for f in files]
    targets: dict[Path, Path] = {}
    for source, target in plan:
        if target in targets:
            raise ScanError(f"{targets[target]} and {source} would both be written to {target}; import them "
                            "into different directories")
        targets[target] = source
        if target.exists() or target.is_symlink():
            raise ScanError(f"{target} already exists; choose another --out or remove it")
    return plan


def import_files(plan: Sequence[tuple[Path, Path]], frequencies_hz: tuple[float, ...] | None = None,
                 variables: Mapping[str, str] | None = None,
                 on_scan: Callable[[Scan, Path], None] | None = None) -> list[Path]:
    """Import every (source, store) pair of :func:`plan_import`: all or nothing.

    Every file is read and validated before the first store is written, so one bad file refuses the whole
    import with its error and nothing is written. Scans that fit :data:`MAX_SCAN_BYTES` together are kept
    from the first pass; the others are read again to be written. ``on_scan(scan, store)`` after each write.
    """
    loaded: list[Scan | None] = []
    held = 0
    for source, _ in plan:
        scan = load_scan_file(source, frequencies_hz, variables)
        size = scan.depth.nbytes + scan.amplitude.nbytes + (0 if scan.taps is None else scan.taps.nbytes)
        keep = held + size <= MAX_SCAN_BYTES
        held += size if keep else 0
        loaded.append(scan if keep else None)
    written = []
    for (source, target), scan in zip(plan, loaded, strict=True):
        scan = scan if scan is not None else load_scan_file(source, frequencies_hz, variables)
        written.append(write_scan(scan, target))
        if on_scan is not None:
            on_scan(scan, target)
    return written
