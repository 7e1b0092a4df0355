"""The scan store: a :class:`~mpi_lidar.scans.scan.Scan` written to and read from Zarr, and the helpers the
other stores share (described arrays, fingerprints, consolidated metadata).

Store (``*.scan.zarr``, Zarr v3, schema ``mpi-lidar/scan@1``): ``depth`` and ``amplitude`` float32
(F, H, W) [m, V^2] with dimensions (frequency, y, x), or raw ``taps`` (F, 4, H, W) [V^2] from which they are
demodulated; optional geometry: ``azimuth_rad`` (W,) and ``elevation_rad`` (H,) of the scan grid, or
``ray_directions`` (H, W, 3) unit vectors; optional ``reference_depth`` (H, W) [m] and ``reference_mask``
(H, W) bool for evaluation. Root attributes: ``schema``, ``frequencies_hz``, ``name``, free ``scene``
metadata, ``depth_wrapped``, ``speed_of_light_m_per_s`` (the c of each frequency's wrap period c / 2f; Table I's
3.0e8 where absent, as in every store written before it) and the chunk fingerprints ``chunk_sha256`` (required:
a scan without them, or without some array's, is damaged; see :mod:`mpi_lidar.storage.integrity`). Every array,
and the root attributes, are declared in :mod:`mpi_lidar.storage.variables` (``docs/reference/stores.md``).

For xarray (``xr.open_zarr``) the store also holds the coordinate ``frequency_hz`` (F,) [Hz] of the frequency
dimension and, where the scan has no azimuth (elevation) grid, the pixel indices ``x`` (``y``); ``azimuth_rad``
and ``elevation_rad`` are coordinates of the pixel columns and rows. Every array carries ``units`` and
``long_name``, and the metadata is consolidated. Readers take the frequencies from the root attributes, and
stores written without these coordinates read the same.
"""

from __future__ import annotations

import warnings
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any, cast

import numpy as np
import zarr
from numpy.typing import DTypeLike, NDArray

from mpi_lidar.constants import TABLE_SPEED_OF_LIGHT_M_PER_S
from mpi_lidar.errors import StoreError
from mpi_lidar.locations import Location, location
from mpi_lidar.scans.scan import (
    OPTIONAL_ARRAYS,
    Scan,
    ScanError,
    check_speed_of_light,
    check_wrap_periods,
    from_taps,
    scan_extras,
    validate,
)
from mpi_lidar.scans.stored_map import StoredMap
from mpi_lidar.storage.atomic import atomic_path
from mpi_lidar.storage.integrity import (
    IntegrityError,
    check_chunk_files,
    check_store_files,
    fingerprint_hex,
    recorded_fingerprints,
    verified_chunks,
    verify_array,
)
from mpi_lidar.storage.objects import list_files, zarr_store
from mpi_lidar.storage.variables import SCAN, Store, attributes
from mpi_lidar.threads import on_cores

if TYPE_CHECKING:
    from zarr.core.common import JSON

SCAN_SCHEMA = "mpi-lidar/scan@1"
SCAN_SUFFIX = ".scan.zarr"
# Every array of a scan together, decoded: depth and amplitude of 4 frequencies x 4096 x 4096 in float32 take
# half of it. Correction holds a few times this while it works, so more would not fit a worker safely.
MAX_SCAN_BYTES = 2**30
MAX_ARRAY_VALUES = 2**28  # 1 GiB of float32 per array: 4 taps x 4 frequencies x 4096 x 4096
# Correction keeps the depth and amplitude of a scan larger than this in its store (:class:`StoredMap`):
# 256 MiB of float32 maps, a 4-frequency scan of about 2900 x 2900.
STORED_MAPS_ABOVE_BYTES = 2**28

# Arrays written for xarray only (see the module docstring); no reader takes data from them.
COORDINATE_ARRAYS = tuple(v.name for v in SCAN.values() if v.coordinate)
# units (UDUNITS) and long_name of every array a scan or corrected store may hold
ARRAY_METADATA: dict[str, tuple[str, str]] = {**attributes(Store.SCAN), **attributes(Store.CORRECTED)}
# The maps a large scan keeps in its store, and the axis of their rows.
_MAP_ROW_AXES = {"depth": 1, "amplitude": 1, "ray_directions": 0}


class DamagedScanError(ScanError, IntegrityError):
    """A scan store whose files, fingerprints or arrays are not those written: both a scan that cannot be read
    and an integrity failure."""


def foreign_store_error(path: object, why: str) -> ScanError:
    """A Zarr store another tool wrote (``why``: no mpi-lidar schema, never fingerprinted): not a damaged scan
    but one to import first, which one line says."""
    return ScanError(f"{path} is not a scan store ({why}); import it first: mpi-lidar import-scan {path} --out DIR")


def write_scan(scan: Scan, path: str | Path, overwrite: bool = False) -> Path:
    """Write a scan store atomically (built beside ``path``, then renamed). Refuses to overwrite by default."""
    path = Path(path)
    scan = validate(scan, str(path))
    check_wrap_periods(scan, str(path))
    if path.exists() and not overwrite:
        raise ScanError(f"{path} already exists; choose another name or remove it")
    with atomic_path(path, replace=overwrite, what="scan", error=ScanError) as staging:
        group = zarr.open_group(store=str(staging), mode="w-", zarr_format=3)
        h, w = scan.shape
        maps = {name: (getattr(scan, name), SCAN[name].dims) for name in ("depth", "amplitude")}
        optional = {name: (np.asarray(getattr(scan, name)), dims) for name, dims in OPTIONAL_ARRAYS.items()
                    if getattr(scan, name) is not None}
        write_described_arrays(group, {**maps, **optional}, scan.shape, scan.frequencies_hz,
                               chunks=dict.fromkeys(maps, (1, min(h, 512), min(w, 512))))
        scene = cast("JSON", scan.scene)  # free metadata that zarr writes as JSON
        group.attrs.update({"schema": SCAN_SCHEMA, "frequencies_hz": [float(f) for f in scan.frequencies_hz],
                            "name": scan.name, "scene": scene, "depth_wrapped": scan.depth_wrapped,
                            "speed_of_light_m_per_s": float(scan.speed_of_light_m_per_s),
                            "chunk_sha256": store_fingerprints(group)})
        consolidate(staging)
    return path


def write_described_arrays(group: zarr.Group, arrays: Mapping[str, tuple[NDArray, tuple[str, ...]]],
                           shape: tuple[int, int], frequencies_hz: Sequence[float] | None = None,
                           metadata: Mapping[str, tuple[str, str]] | None = None,
                           chunks: Mapping[str, tuple[int, ...]] | None = None,
                           attributes: Mapping[str, Mapping[str, JSON]] | None = None) -> None:
    """Write data arrays (name -> (values, dimension names)) so that xarray reads the store: with coordinate
    arrays, and ``units``, ``long_name`` and ``coordinates`` on every array.

    Adds ``frequency_hz`` (with ``frequencies_hz`` given) and the pixel indices ``y``/``x`` of a grid without
    ``elevation_rad``/``azimuth_rad``. Each array is described from :data:`ARRAY_METADATA` and ``metadata``
    (name -> (units, long_name)), plus its own ``attributes``, in the one metadata write that creates it;
    ``chunks`` where an array's chunks are not zarr's own choice. Write the fingerprints after it.
    """
    h, w = shape
    planned: dict[str, tuple[NDArray, tuple[str, ...]]] = dict(arrays)
    if frequencies_hz is not None:
        planned["frequency_hz"] = (np.asarray(frequencies_hz, dtype=np.float64), ("frequency",))
    for index, grid, size in (("y", "elevation_rad", h), ("x", "azimuth_rad", w)):
        if grid not in planned:
            planned[index] = (np.arange(size, dtype=np.int64), (index,))
    described = {**ARRAY_METADATA, **(metadata or {})}
    coordinates = [name for name in ("frequency_hz", "elevation_rad", "azimuth_rad") if name in planned]
    for name, (values, dims) in planned.items():
        units, long_name = described.get(name, ("1", name.replace("_", " ")))
        attrs: dict[str, JSON] = {"units": units, "long_name": long_name, **(attributes or {}).get(name, {})}
        if name not in coordinates and name not in dims:
            own = " ".join(c for c in coordinates if set(planned[c][1]) <= set(dims))
            if own:
                attrs["coordinates"] = own
        group.create_array(name, data=values, dimension_names=dims, attributes=attrs,
                           chunks=chunks[name] if chunks and name in chunks else "auto")


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

    The scan's speed of light is the store's ``speed_of_light_m_per_s``, or ``c`` [m/s] for a store written
    before it (Table I's 3.0e8, as they all were). A wrapped scan whose depth passes a frequency's wrap period is
    refused (:func:`~mpi_lidar.scans.scan.check_wrap_periods`).

    A store whose depth and amplitude (and ray directions) take more than ``stored_above_bytes`` as float32
    keeps them in the store: they come as :class:`StoredMap`, every chunk checked against its fingerprint
    here (one chunk at a time) and read again where correction needs it, a band of rows at a time.
    """
    where = location(path)
    path = Path(where.path) if where.is_local else where.url  # a URL names the scan in every message
    files = _store_files(where)
    try:
        # Each array's own metadata, not the consolidated copy: that is what the chunks were written with.
        # In an object store, v3 only: zarr would otherwise look for v2 metadata too, four requests more.
        group = zarr.open_group(store=zarr_store(where), mode="r", use_consolidated=False,
                                zarr_format=None if where.is_local else 3)
        attrs: dict[str, Any] = dict(group.attrs)  # JSON as stored: checked where it is used
        arrays = dict(group.arrays())  # opened together: one round trip to the store, not one per array
        members = set(arrays)
    except Exception as exc:  # zarr raises several types for foreign or broken metadata
        raise ScanError(f"{path} is not a readable Zarr store ({type(exc).__name__})") from None
    if attrs.get("schema") != SCAN_SCHEMA:
        raise foreign_store_error(path, f"schema {attrs.get('schema')!r}, expected {SCAN_SCHEMA!r}")
    if not {"chunk_sha256", "depth_wrapped"} & set(attrs):  # this package writes both, with the arrays
        raise foreign_store_error(path, "it was never fingerprinted, so another tool wrote it")
    try:
        _check_declared_sizes(path, arrays)
        frequencies = tuple(float(f) for f in attrs["frequencies_hz"])
        try:
            check_chunk_files(path, files, arrays)
            # Every array's, as every scan of this schema records them: a scan without them is damaged, not old.
            fingerprints = recorded_fingerprints(path, attrs.get("chunk_sha256"), arrays)
        except IntegrityError as exc:
            raise DamagedScanError(str(exc)) from None

        in_store = {"depth", "amplitude"} <= members and stored_above_bytes < 4 * sum(
            np.prod(arrays[name].shape, dtype=np.float64) for name in _MAP_ROW_AXES if name in members)

        def read(name: str) -> NDArray:
            if in_store and name in _MAP_ROW_AXES:
                for _ in verified_chunks(arrays[name], fingerprints[name], str(path), name):
                    pass
                # The maps come as float32 (as validate makes them), ray directions as stored.
                return _standing_in(StoredMap(arrays[name], _MAP_ROW_AXES[name],
                                              None if name == "ray_directions" else np.float32,
                                              fingerprints[name], str(path), name))
            return verify_array(arrays[name], fingerprints[name], str(path), name)

        optional = {name: read(name) for name in OPTIONAL_ARRAYS if name in members}
        coordinates = {name: read(name) for name in COORDINATE_ARRAYS if name in members}
        if "frequency_hz" in coordinates and not np.array_equal(coordinates["frequency_hz"], frequencies):
            raise ScanError(f"{path}: its frequency_hz array {coordinates['frequency_hz'].tolist()} differs from "
                            f"its frequencies_hz attribute {list(frequencies)}; the store was altered")
        name = str(attrs.get("name") or where.name.removesuffix(SCAN_SUFFIX))
        scene = attrs.get("scene") or {}
        wrapped = attrs.get("depth_wrapped", True)  # absent in scans written before unwrapping: as measured
        if not isinstance(wrapped, bool):
            raise ScanError(f"{path}: its depth_wrapped attribute is {wrapped!r}, not true or false; the store was "
                            "altered")
        # Absent in stores written before it, all made with Table I's c (or ``c``, which demodulates taps).
        light = check_speed_of_light(attrs.get("speed_of_light_m_per_s", c), str(path))
        if {"depth", "amplitude"} <= members:
            scan = Scan(name=name, frequencies_hz=frequencies, depth=read("depth"), amplitude=read("amplitude"),
                        taps=optional.get("taps"), scene=scene, depth_wrapped=wrapped,
                        speed_of_light_m_per_s=light, **scan_extras(optional))
        elif "taps" in members:
            scan = from_taps(name, frequencies, optional["taps"], light, scene=scene, **scan_extras(optional))
        else:
            raise ScanError(f"{path} has neither depth+amplitude nor taps; it is truncated or not a scan")
    except StoreError:  # ScanError and IntegrityError: already one clear line
        raise
    except (KeyError, ValueError, TypeError, OSError, RuntimeError) as exc:  # codecs raise RuntimeError
        reason = str(exc).splitlines()[0] if str(exc) else ""
        raise ScanError(f"{path} is damaged or truncated ({type(exc).__name__}: {reason})") from None
    scan = validate(scan, str(path))
    check_wrap_periods(scan, str(path))
    return scan


def _standing_in(stored: StoredMap) -> NDArray:
    """A stored map where the scan holds an array: it reads like one (``shape``, ``dtype``, slicing,
    ``np.asarray``), and the code that needs to tell them apart asks ``isinstance(..., StoredMap)``."""
    return cast("NDArray", stored)


def _store_files(where: Location) -> dict[str, int]:
    """Every file (object) of a scan store with its size, after refusing links, FIFOs, devices and oversized
    metadata (before zarr opens anything); a store that does not exist is refused with one line."""
    try:
        if where.is_local:
            path = where.local_path()
            if not path.exists():
                raise ScanError(f"scan {path} does not exist")
            return check_store_files(path) if path.is_dir() else {}
        files = list_files(where)
    except IntegrityError as exc:
        raise DamagedScanError(str(exc)) from None
    if "zarr.json" not in files:
        raise ScanError(f"scan {where} does not exist")
    return files


def _check_declared_sizes(path: Path | str, arrays: Mapping[str, zarr.Array]) -> None:
    """Refuse a store whose declared arrays exceed the memory budget, before allocating anything.

    A damaged or hostile store can declare 4 x 8000 x 8000 pixels in a few hundred bytes of metadata.
    """
    check_memory_budget(path, [(f"array {name!r}", array.shape, array.dtype) for name, array in arrays.items()])


def check_memory_budget(path: Path | str, declared: Sequence[tuple[str, tuple[int, ...], DTypeLike]]) -> None:
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

