"""Scans: depth and amplitude maps at several frequencies, the scanner geometry, and an optional reference.

Store (``*.scan.zarr``, Zarr v3, schema ``mpi-lidar/scan@1``): ``depth`` and ``amplitude`` float32
(F, H, W) [m, V^2] with dimensions (frequency, y, x), or raw ``taps`` (F, 4, H, W) [V^2] from which they are
demodulated; optional geometry: ``azimuth_rad`` (W,) and ``elevation_rad`` (H,) of the scan grid, or
``ray_directions`` (H, W, 3) unit vectors; optional ``reference_depth`` (H, W) [m] and ``reference_mask``
(H, W) bool for evaluation. Root attributes: ``schema``, ``frequencies_hz``, ``name`` and free ``scene``
metadata.

Geometry convention: the scanner sits at the origin; x right, y up, z forward. The ray of azimuth a and
elevation e is (cos e sin a, sin e, cos e cos a); depth is the range along the ray.
"""

from __future__ import annotations

import hashlib
import json
import zipfile
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np
import zarr
from numpy.typing import NDArray

from mpi_lidar.constants import TABLE_SPEED_OF_LIGHT_M_PER_S
from mpi_lidar.errors import StoreError
from mpi_lidar.physics import demod
from mpi_lidar.storage.atomic import atomic_path
from mpi_lidar.storage.integrity import array_fingerprints, verify_array

SCAN_SCHEMA = "mpi-lidar/scan@1"
SCAN_SUFFIX = ".scan.zarr"
# Every array of a scan together, decoded: depth and amplitude of 4 frequencies x 4096 x 4096 in float32 take
# half of it. Correction holds a few times this while it works, so more would not fit a worker safely.
MAX_SCAN_BYTES = 2**30
MAX_ARRAY_VALUES = 2**28  # 1 GiB of float32 per array: 4 taps x 4 frequencies x 4096 x 4096


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

    def raw_pixels(self) -> NDArray[np.float32]:
        """Per-pixel raw measurements (H*W, 2F) ordered like a dataset's features: depths, then amplitudes."""
        f = len(self.frequencies_hz)
        stacked = np.concatenate([self.depth.reshape(f, -1), self.amplitude.reshape(f, -1)], axis=0)
        return np.ascontiguousarray(stacked.T, dtype=np.float32)

    def content_sha256(self) -> str:
        """Identity of what correction reads: frequencies, depth and amplitude maps, geometry."""
        digest = hashlib.sha256(json.dumps([float(f) for f in self.frequencies_hz]).encode())
        for array in (self.depth, self.amplitude, self.azimuth_rad, self.elevation_rad, self.ray_directions):
            if array is not None:
                digest.update(np.ascontiguousarray(array).tobytes())
        return digest.hexdigest()


def grid_rays(azimuth_rad: NDArray, elevation_rad: NDArray) -> NDArray[np.float64]:
    """Unit rays (H, W, 3) of an azimuth (W,) by elevation (H,) scan grid."""
    az = np.asarray(azimuth_rad, dtype=np.float64)[None, :]
    el = np.asarray(elevation_rad, dtype=np.float64)[:, None]
    return np.stack([np.cos(el) * np.sin(az), np.sin(el) * np.ones_like(az), np.cos(el) * np.cos(az)], axis=-1)


def validate(scan: Scan, source: str) -> Scan:
    """Check shapes, dtypes and values; return the scan with float32 maps. One clear error per problem."""
    f = len(scan.frequencies_hz)
    if f == 0 or any(not np.isfinite(x) or x <= 0 for x in scan.frequencies_hz):
        raise ScanError(f"{source}: frequencies_hz must be positive numbers, got {list(scan.frequencies_hz)}")
    if len(set(scan.frequencies_hz)) != f:
        raise ScanError(f"{source}: frequencies_hz has duplicates {list(scan.frequencies_hz)}; each frequency "
                        "is measured once")
    depth, amplitude = np.asarray(scan.depth), np.asarray(scan.amplitude)
    if depth.ndim != 3 or depth.shape[0] != f:
        raise ScanError(f"{source}: depth must have shape (F={f}, H, W), got {depth.shape}")
    if amplitude.shape != depth.shape:
        raise ScanError(f"{source}: amplitude shape {amplitude.shape} differs from depth shape {depth.shape}")
    for name, array in (("depth", depth), ("amplitude", amplitude)):
        if not np.issubdtype(array.dtype, np.floating):
            raise ScanError(f"{source}: {name} must be floating point, got {array.dtype}")
    if np.any(amplitude < 0):
        raise ScanError(f"{source}: amplitude has negative values ({int((amplitude < 0).sum())} pixels); an "
                        "amplitude is a magnitude: check the importer or the tap order")
    if not np.isfinite(depth).any():
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
        if value is not None and not np.issubdtype(np.asarray(value).dtype, np.floating):
            raise ScanError(f"{source}: {name} must be floating point, got {np.asarray(value).dtype}")
    return replace(scan, depth=depth.astype(np.float32, copy=False), amplitude=amplitude.astype(np.float32, copy=False))


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


def write_scan(scan: Scan, path: str | Path, overwrite: bool = False) -> Path:
    """Write a scan store atomically (built beside ``path``, then renamed). Refuses to overwrite by default."""
    path = Path(path)
    scan = validate(scan, str(path))
    if path.exists() and not overwrite:
        raise ScanError(f"{path} already exists; choose another name or remove it")
    with atomic_path(path, replace=overwrite, what="scan", error=ScanError) as staging:
        group = zarr.open_group(store=str(staging), mode="w-")
        h, w = scan.shape
        chunks = (1, min(h, 512), min(w, 512))
        for name in ("depth", "amplitude"):
            group.create_array(name, data=getattr(scan, name), chunks=chunks, dimension_names=("frequency", "y", "x"))
        for name, dims in OPTIONAL_ARRAYS.items():
            value = getattr(scan, name)
            if value is not None:
                group.create_array(name, data=np.asarray(value), dimension_names=dims)
        group.attrs.update({"schema": SCAN_SCHEMA, "frequencies_hz": [float(f) for f in scan.frequencies_hz],
                            "name": scan.name, "scene": scan.scene, "chunk_sha256": store_fingerprints(group)})
    return path


def store_fingerprints(group: zarr.Group) -> dict[str, list[str]]:
    """Fingerprints of every chunk of every array of a store just written (read back, so exactly as stored)."""
    return {name: array_fingerprints(group[name][...], group[name].chunks) for name in sorted(group.array_keys())}


def read_scan(path: str | Path, c: float = TABLE_SPEED_OF_LIGHT_M_PER_S) -> Scan:
    """Read and validate a scan store; depth/amplitude are demodulated from taps when only taps are stored."""
    path = Path(path)
    if not path.exists():
        raise ScanError(f"scan {path} does not exist")
    try:
        group = zarr.open_group(store=str(path), mode="r")
        attrs = dict(group.attrs)
        members = set(group.array_keys())
    except Exception as exc:  # zarr raises several types for foreign or broken metadata
        raise ScanError(f"{path} is not a readable Zarr store ({type(exc).__name__})") from None
    if attrs.get("schema") != SCAN_SCHEMA:
        raise ScanError(f"{path} is not an mpi-lidar scan (schema {attrs.get('schema')!r}, expected {SCAN_SCHEMA!r})")
    try:
        _check_declared_sizes(path, group, members)
        frequencies = tuple(float(f) for f in attrs["frequencies_hz"])
        fingerprints = attrs.get("chunk_sha256")  # absent in scans written before fingerprints existed
        fingerprints = fingerprints if isinstance(fingerprints, dict) else {}

        def read(name: str) -> NDArray:
            return verify_array(group[name], fingerprints.get(name), str(path), name)

        optional = {name: read(name) for name in OPTIONAL_ARRAYS if name in members}
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


def _check_declared_sizes(path: Path, group: zarr.Group, members: set[str]) -> None:
    """Refuse a store whose declared arrays exceed the memory budget, before allocating anything.

    A damaged or hostile store can declare 4 x 8000 x 8000 pixels in a few hundred bytes of metadata.
    """
    total = 0
    for name in members:
        array = group[name]
        values = float(np.prod(array.shape, dtype=np.float64))
        if values > MAX_ARRAY_VALUES:
            raise ScanError(f"{path}: array {name!r} declares shape {array.shape}, more than the "
                            f"{MAX_ARRAY_VALUES:,} values a scan array may hold; the store is damaged")
        total += values * array.dtype.itemsize
    if total > MAX_SCAN_BYTES:
        raise ScanError(f"{path}: its arrays declare {total / 2**30:.1f} GiB, more than the {MAX_SCAN_BYTES / 2**30:g} "
                        "GiB a scan may hold in memory; split the scan into smaller ones")


def import_arrays(
    name: str, frequencies_hz: tuple[float, ...], arrays: dict[str, NDArray], c: float = TABLE_SPEED_OF_LIGHT_M_PER_S
) -> Scan:
    """A scan from plain arrays (e.g. an ``.npz`` from another tool): depth+amplitude or taps, plus extras."""
    known = {"depth", "amplitude", *OPTIONAL_ARRAYS}
    unknown = sorted(set(arrays) - known - {"frequencies_hz"})
    if unknown:
        raise ScanError(f"{name}: unknown arrays {unknown}; expected some of {sorted(known)}")
    optional = {k: np.asarray(v) for k, v in arrays.items() if k in OPTIONAL_ARRAYS and k != "taps"}
    if "reference_mask" in optional:
        optional["reference_mask"] = _boolean_mask(name, optional["reference_mask"])
    if "depth" in arrays and "amplitude" in arrays:
        scan = Scan(name=name, frequencies_hz=tuple(frequencies_hz), depth=np.asarray(arrays["depth"]),
                    amplitude=np.asarray(arrays["amplitude"]), taps=arrays.get("taps"), **optional)
    elif "taps" in arrays:
        scan = from_taps(name, tuple(frequencies_hz), np.asarray(arrays["taps"]), c, **optional)
    else:
        raise ScanError(f"{name}: needs arrays 'depth' and 'amplitude' (F, H, W), or 'taps' (F, 4, H, W)")
    return validate(scan, name)


def _boolean_mask(name: str, mask: NDArray) -> NDArray[np.bool_]:
    """A 0/1 mask of any numeric type as booleans; anything else is refused rather than guessed."""
    if mask.dtype != np.bool_ and not (np.issubdtype(mask.dtype, np.number) and np.isin(mask, (0, 1)).all()):
        raise ScanError(f"{name}: reference_mask must be boolean or 0/1, got {mask.dtype} with other values")
    return mask.astype(bool)


def load_npz(path: str | Path, frequencies_hz: tuple[float, ...] | None = None) -> Scan:
    """Import an ``.npz`` archive (arrays named as in the scan store; frequencies_hz inside or given).

    Every member's header is checked (dtype, declared size against the memory budget) before any array
    is read, so a damaged or hostile archive is refused without allocating what it claims.
    """
    path = Path(path)
    _check_npz_headers(path)
    try:
        with np.load(path, allow_pickle=False) as archive:
            arrays = {key: archive[key] for key in archive.files}
    except Exception as exc:  # zipfile, numpy and OS errors of a damaged archive
        raise ScanError(f"{path} is not a readable .npz archive ({type(exc).__name__}: {exc})") from None
    stored = arrays.pop("frequencies_hz", None)
    if frequencies_hz is None and stored is None:
        raise ScanError(f"{path} holds no frequencies_hz array; pass --frequencies")
    freqs = frequencies_hz if frequencies_hz is not None else _stored_frequencies(path, stored)
    return import_arrays(path.name.removesuffix(".npz"), tuple(float(f) for f in freqs), arrays)


def _stored_frequencies(path: Path, stored: NDArray) -> NDArray:
    if stored.ndim != 1 or stored.size == 0 or not np.issubdtype(stored.dtype, np.number):
        raise ScanError(f"{path}: frequencies_hz must be a 1-D array of numbers in Hz, got "
                        f"{stored.dtype}{stored.shape}; pass --frequencies instead")
    return stored


def _check_npz_headers(path: Path) -> None:
    """Refuse members that are not plain numeric arrays, or that declare more than a scan may hold."""
    try:
        with zipfile.ZipFile(path) as archive:
            total = 0.0
            for info in archive.infolist():
                with archive.open(info) as member:
                    version = np.lib.format.read_magic(member)
                    read_header = (np.lib.format.read_array_header_1_0 if version == (1, 0)
                                   else np.lib.format.read_array_header_2_0)
                    shape, _, dtype = read_header(member)
                if dtype.hasobject or dtype.kind not in "biuf":
                    raise ScanError(f"{path}: member {info.filename} has dtype {dtype}; only numbers and booleans "
                                    "can be imported")
                total += float(np.prod(shape, dtype=np.float64)) * dtype.itemsize
    except ScanError:
        raise
    except Exception as exc:  # not a zip, a member without an .npy header, a damaged header
        raise ScanError(f"{path} is not a readable .npz archive ({type(exc).__name__}: {exc})") from None
    if total > MAX_SCAN_BYTES:
        raise ScanError(f"{path}: its arrays declare {total / 2**30:.1f} GiB, more than the "
                        f"{MAX_SCAN_BYTES / 2**30:g} GiB a scan may hold in memory; split the scan into smaller ones")
