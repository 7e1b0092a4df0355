"""Scans in memory: depth and amplitude maps at several frequencies, the scanner geometry, an optional reference.

A :class:`Scan` holds depth and amplitude (F, H, W) [m, V^2] at F modulation frequencies; optional geometry:
``azimuth_rad`` (W,) and ``elevation_rad`` (H,) of the scan grid, or ``ray_directions`` (H, W, 3) unit
vectors; optional ``reference_depth`` (H, W) [m] and ``reference_mask`` (H, W) bool for evaluation; raw
``taps`` (F, 4, H, W) [V^2] where it was demodulated from them (:func:`from_taps`); the speed of light its
depths were converted from phases with [m/s], which sets each frequency's wrap period c / 2f. Every array is declared in
:mod:`mpi_lidar.storage.variables`, which :func:`validate` checks against. The store is
:mod:`mpi_lidar.scans.store`, the importers of other formats :mod:`mpi_lidar.scans.importers`.

Geometry convention: the scanner sits at the origin; x towards positive azimuth (to the scanner's left:
right-handed), y up, z forward. The ray of azimuth a and elevation e is (cos e sin a, sin e, cos e cos a); depth
is the range along the ray.
"""

from __future__ import annotations

import hashlib
import json
from collections.abc import Iterator, Mapping
from dataclasses import dataclass, field, replace
from typing import TypedDict, Unpack

import numpy as np
from numpy.typing import NDArray

from mpi_lidar.constants import TABLE_SPEED_OF_LIGHT_M_PER_S
from mpi_lidar.errors import StoreError
from mpi_lidar.physics import demod
from mpi_lidar.scans.stored_map import StoredMap
from mpi_lidar.storage.variables import FIXED_SIZES, SCAN

# The optional arrays of a scan (neither required nor a coordinate), in the order they are checked.
OPTIONAL_ARRAYS: dict[str, tuple[str, ...]] = {
    v.name: v.dims for v in SCAN.values() if not v.required and not v.coordinate}


# The speeds of light a scanner's firmware may convert phases to ranges with [m/s]: the physical value
# 299,792,458 m/s, Table I's 3.0e8, or a value for air; anything outside is a wrong number or a wrong unit.
SPEED_OF_LIGHT_BOUNDS_M_PER_S = (2.9e8, 3.1e8)
# How far a wrapped depth may pass its frequency's wrap period before the period is wrong: a relative share of
# the period [1] plus an absolute margin [m] (float32 rounding and a phase of 2 pi read back as one of 0).
WRAP_TOLERANCE = (1e-3, 1e-3)
# A near surface's depth passes zero by its noise, wrapped or not (a scanner's own zero-range offset removed):
# correction flags each pixel more than NOISE_DEVIATIONS of its own noise below zero (the validity stage, under the
# scan's noise law). What no noise explains refuses the scan where it is read: a depth below NOISE_DEVIATIONS
# deviations of the noisiest return a scan keeps, one at the lowest frequency whose amplitude is
# WEAKEST_RETURN_SNR times its noise (the no-return threshold's default), whose phase deviates by 1 / SNR [rad].
NOISE_DEVIATIONS = 3.0
WEAKEST_RETURN_SNR = 5.0
# The scan grid's angles [rad]: an azimuth within one turn either way, an elevation within the poles.
ANGLE_LIMITS_RAD = {"azimuth_rad": 2 * np.pi, "elevation_rad": np.pi / 2}
# How far a ray direction's length may be from 1 (float32 rounding of a unit vector).
RAY_NORM_TOLERANCE = 1e-3


class ScanError(StoreError):
    """A scan that cannot be read or used."""


class ScanExtras(TypedDict, total=False):
    """The optional arrays of a scan other than its taps: keyword arguments of :class:`Scan` and :func:`from_taps`."""

    azimuth_rad: NDArray[np.float64] | None
    elevation_rad: NDArray[np.float64] | None
    ray_directions: NDArray[np.float32] | None
    reference_depth: NDArray[np.float32] | None
    reference_mask: NDArray[np.bool_] | None


def scan_extras(arrays: Mapping[str, NDArray]) -> ScanExtras:
    """The optional arrays (other than taps) among ``arrays``, by name; the others are None."""
    return ScanExtras(azimuth_rad=arrays.get("azimuth_rad"), elevation_rad=arrays.get("elevation_rad"),
                      ray_directions=arrays.get("ray_directions"), reference_depth=arrays.get("reference_depth"),
                      reference_mask=arrays.get("reference_mask"))


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
    # Whether each frequency's depth is wrapped into [0, c / 2f), as a phase measures it (True), or already
    # unwrapped into one range by the scanner (False). Under the highest frequency's ambiguity distance
    # (4.8 m at 31.25 MHz) the two are the same.
    depth_wrapped: bool = True
    # The speed of light the scanner converted phase to range with [m/s]: each frequency's depth wraps at
    # c / 2f. Scans of the simulator record its own (Table I's 3.0e8 by default).
    speed_of_light_m_per_s: float = TABLE_SPEED_OF_LIGHT_M_PER_S

    @property
    def wrap_periods_m(self) -> tuple[float, ...]:
        """Each frequency's wrap period c / 2f, the depth at which its phase wraps. [m]"""
        return tuple(float(p) for p in demod.unambiguous_range(self.frequencies_hz, self.speed_of_light_m_per_s))

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
        """Whether the depth and amplitude maps are in memory, not read from the store (:class:`StoredMap`, or a
        view of one that says so with ``in_store``)."""
        return not any(isinstance(maps, StoredMap) or getattr(maps, "in_store", False)
                       for maps in (self.depth, self.amplitude))

    def content_sha256(self) -> str:
        """Identity of what correction reads: frequencies, depth and amplitude maps (whether the depths are
        wrapped, and the speed of light they were converted with), geometry."""
        digest = hashlib.sha256(json.dumps([float(f) for f in self.frequencies_hz]).encode())
        if not self.depth_wrapped:  # the common case leaves the identities of earlier scans as they were
            digest.update(b"depth unwrapped")
        if self.speed_of_light_m_per_s != TABLE_SPEED_OF_LIGHT_M_PER_S:  # as above: Table I's c adds nothing
            digest.update(json.dumps({"speed_of_light_m_per_s": float(self.speed_of_light_m_per_s)}).encode())
        for array in (self.depth, self.amplitude, self.azimuth_rad, self.elevation_rad, self.ray_directions):
            parts = array.c_order_parts() if isinstance(array, StoredMap) else [] if array is None else [array]
            for part in parts:
                digest.update(np.ascontiguousarray(part).reshape(-1).view(np.uint8).data)  # no copy of the bytes
        return digest.hexdigest()


def grid_rays(azimuth_rad: NDArray, elevation_rad: NDArray, pairs: bool = False) -> NDArray[np.float64]:
    """Unit rays (H, W, 3) of an azimuth (W,) by elevation (H,) scan grid; with ``pairs``, the rays (n, 3) of
    n (azimuth, elevation) pairs."""
    az = np.asarray(azimuth_rad, dtype=np.float64)
    el = np.asarray(elevation_rad, dtype=np.float64)
    if not pairs:
        az, el = az[None, :], el[:, None]
    return np.stack([np.cos(el) * np.sin(az), np.sin(el) * np.ones_like(az), np.cos(el) * np.cos(az)], axis=-1)


class RayRows:
    """A scan's unit rays (H, W, 3), built for a band of rows when sliced (``rays[top:bottom]``): a large
    scan never holds all of them in float64 at once. Each row is exactly that row of :meth:`Scan.rays`."""

    def __init__(self, scan: Scan):
        self.scan = scan
        self.shape = (*scan.shape, 3)

    def __getitem__(self, rows: slice) -> NDArray[np.float64]:
        scan = self.scan
        if scan.ray_directions is not None:
            return np.asarray(scan.ray_directions[rows], dtype=np.float64)
        if scan.azimuth_rad is None or scan.elevation_rad is None:  # Scan.ray_rows gives none then
            raise ValueError(f"scan {scan.name} has no geometry")
        return grid_rays(scan.azimuth_rad, np.asarray(scan.elevation_rad)[rows])


def validate(scan: Scan, source: str) -> Scan:
    """Check shapes, dtypes and values; return the scan with float32 maps. One clear error per problem."""
    f = len(scan.frequencies_hz)
    if f == 0 or any(not np.isfinite(x) or x <= 0 for x in scan.frequencies_hz):
        raise ScanError(f"{source}: frequencies_hz must be positive numbers, got {list(scan.frequencies_hz)}")
    if len(set(scan.frequencies_hz)) != f:
        raise ScanError(f"{source}: frequencies_hz has duplicates {list(scan.frequencies_hz)}; each frequency "
                        "is measured once")
    check_speed_of_light(scan.speed_of_light_m_per_s, source)
    stored = isinstance(scan.depth, StoredMap) and isinstance(scan.amplitude, StoredMap)
    depth: NDArray | StoredMap = scan.depth if stored else np.asarray(scan.depth)
    amplitude: NDArray | StoredMap = scan.amplitude if stored else np.asarray(scan.amplitude)
    if depth.ndim != 3 or depth.shape[0] != f:
        raise ScanError(f"{source}: depth must have shape (F={f}, H, W), got {depth.shape}")
    if amplitude.shape != depth.shape:
        raise ScanError(f"{source}: amplitude shape {amplitude.shape} differs from depth shape {depth.shape}")
    for name, array in (("depth", depth), ("amplitude", amplitude)):
        _check_dtype(source, name, array)
    _check_amplitudes(amplitude, source)
    if not any(np.isfinite(part).any() for part in _parts(depth)):
        raise ScanError(f"{source}: no pixel has a finite depth")
    sizes = {"frequency": f, "y": depth.shape[1], "x": depth.shape[2], **FIXED_SIZES}
    for name in OPTIONAL_ARRAYS:
        value = getattr(scan, name)
        if value is not None and np.shape(value) != SCAN[name].shape(sizes):
            raise ScanError(f"{source}: {name} must have shape {SCAN[name].shape(sizes)}, got {np.shape(value)}")
    for name in sorted(OPTIONAL_ARRAYS, key=lambda name: SCAN[name].kind != "b"):  # the boolean mask first
        value = getattr(scan, name)
        if value is not None:
            _check_dtype(source, name, value)
    check_geometry_values({name: value for name in ("azimuth_rad", "elevation_rad", "ray_directions")
                           if (value := getattr(scan, name)) is not None}, source)
    if not isinstance(depth, StoredMap) and not isinstance(amplitude, StoredMap):
        return replace(scan, depth=depth.astype(np.float32, copy=False),
                       amplitude=amplitude.astype(np.float32, copy=False))
    return scan


def _check_amplitudes(amplitude: NDArray | StoredMap, source: str) -> None:
    """Refuse negative amplitudes, and one positive amplitude over the whole scan: a magnitude that varies with
    nothing is no measurement (a fill value, or a channel mapped wrong). NaN and infinite ones are flagged by
    correction (not finite); amplitudes all 0 are a scan without a return (flagged no return)."""
    negative, low, high = 0, np.inf, -np.inf
    for part in _parts(amplitude):
        negative += int((part < 0).sum())
        finite = part[np.isfinite(part)]
        if finite.size:
            low, high = min(low, float(finite.min())), max(high, float(finite.max()))
    if negative:
        raise ScanError(f"{source}: amplitude has negative values ({negative} pixels); an "
                        "amplitude is a magnitude: check the importer or the tap order")
    if int(np.prod(amplitude.shape)) > 1 and low == high and low > 0:
        raise ScanError(f"{source}: every finite amplitude is {low:g}: a constant is no measurement of a return's "
                        "strength; import the scanner's amplitude (or intensity) channel")


def check_geometry_values(arrays: Mapping[str, NDArray | StoredMap], source: str) -> None:
    """Refuse scan-grid angles that are not finite radians within :data:`ANGLE_LIMITS_RAD` (azimuth within
    +-2 pi, elevation within +-pi/2: beyond that they are degrees), and ray directions that are not finite unit
    vectors (within :data:`RAY_NORM_TOLERANCE`)."""
    for name, limit in ANGLE_LIMITS_RAD.items():
        if name not in arrays:
            continue
        values = np.asarray(arrays[name], dtype=np.float64)
        if not np.isfinite(values).all():
            where = "column" if name == "azimuth_rad" else "row"
            raise ScanError(f"{source}: {name} has values that are not finite ({int((~np.isfinite(values)).sum())} "
                            f"pixel {where}s); every pixel {where} needs its angle")
        largest = float(np.abs(values).max(initial=0.0))
        if largest > limit * (1 + 1e-9):
            degrees = name.replace("_rad", "_deg")
            raise ScanError(f"{source}: {name} reaches {largest:g}, beyond the {limit:.4g} rad an angle of the scan "
                            f"grid can be, so it is in degrees; import it with --var {degrees}=VARIABLE (or a "
                            "NetCDF units attribute 'degrees')")
    if "ray_directions" in arrays:
        for part in _parts(arrays["ray_directions"]):
            rays = np.asarray(part, dtype=np.float64)
            if not np.isfinite(rays).all():
                raise ScanError(f"{source}: ray_directions has values that are not finite; every pixel needs its "
                                "ray")
            off = float(np.abs(np.sqrt((rays**2).sum(axis=-1)) - 1).max(initial=0.0))
            if off > RAY_NORM_TOLERANCE:
                raise ScanError(f"{source}: ray_directions are not unit vectors (lengths up to {1 + off:.4g}); "
                                "divide each by its length before importing")


def check_speed_of_light(c: object, source: str) -> float:
    """The speed of light a scan's phases were converted with [m/s], checked: a finite number within
    :data:`SPEED_OF_LIGHT_BOUNDS_M_PER_S`."""
    low, high = SPEED_OF_LIGHT_BOUNDS_M_PER_S
    if isinstance(c, bool) or not isinstance(c, int | float | np.floating | np.integer) or not low <= c <= high:
        raise ScanError(f"{source}: speed_of_light_m_per_s is {c!r}, not a speed of light in m/s within "
                        f"{low:.3g}-{high:.3g}; give the one the scanner converted phase to range with (299792458 "
                        "in vacuum)")
    return float(c)


def lowest_depth_m(frequencies_hz: tuple[float, ...], c: float) -> float:
    """The lowest depth any pixel of a scan may hold [m]: :data:`NOISE_DEVIATIONS` deviations below zero of the
    noisiest return it keeps, c / (4 pi f) / :data:`WEAKEST_RETURN_SNR` at its lowest frequency f [Hz] (1.15 m at
    12.5 MHz). Each pixel is held to its own noise by correction."""
    return -NOISE_DEVIATIONS * c / (4 * np.pi * min(frequencies_hz)) / WEAKEST_RETURN_SNR


def check_wrap_periods(scan: Scan, source: str) -> None:
    """Refuse depths outside what a scanner measures: below :func:`lowest_depth_m` (a negative range no noise
    explains), and, in a wrapped scan, a finite depth at some frequency past that frequency's wrap period c / 2f
    (beyond :data:`WRAP_TOLERANCE`): its depths are unwrapped already, or were converted with another c."""
    lowest = min((float(part[np.isfinite(part)].min(initial=np.inf)) for part in _parts(scan.depth)),
                 default=np.inf)
    floor = lowest_depth_m(scan.frequencies_hz, scan.speed_of_light_m_per_s)
    if lowest < floor:
        raise ScanError(f"{source}: its depth reaches {lowest:.4g} m: a range passes zero by its noise, never by more "
                        f"than {-floor:.3g} m ({NOISE_DEVIATIONS:g} deviations of its noisiest return); import the "
                        "scanner's ranges (distances from the scanner, in metres) as they are")
    if not scan.depth_wrapped:
        return
    relative, absolute = WRAP_TOLERANCE
    maxima = _largest_per_frequency(scan.depth)
    for f, period, largest in zip(scan.frequencies_hz, scan.wrap_periods_m, maxima, strict=True):
        if largest > period * (1 + relative) + absolute:
            raise ScanError(f"{source}: its depth at {f / 1e6:g} MHz reaches {largest:.4f} m, beyond that "
                            f"frequency's wrap period {period:.4f} m (c / 2f with c = "
                            f"{scan.speed_of_light_m_per_s:.9g} m/s); give the speed of light the scanner used "
                            "(import-scan --speed-of-light M_PER_S), or import depths the scanner unwrapped with "
                            "--depths unwrapped")


def _largest_per_frequency(depth: NDArray | StoredMap) -> list[float]:
    """The largest finite depth (F,) of each frequency's map [m] (-inf where none is finite); a stored map is
    read a band of one frequency's rows at a time, past the band it keeps for correction's tiles."""
    largest = np.full(depth.shape[0], -np.inf)
    if isinstance(depth, StoredMap):  # its parts: each frequency's bands of rows, frequency by frequency
        per_frequency = len(depth.row_bands())
        for index, part in enumerate(depth.c_order_parts()):
            finite = np.where(np.isfinite(part), part, -np.inf)
            largest[index // per_frequency] = max(largest[index // per_frequency], finite.max(initial=-np.inf))
        return [float(x) for x in largest]
    values = np.asarray(depth).reshape(depth.shape[0], -1)
    return [float(x) for x in np.where(np.isfinite(values), values, -np.inf).max(axis=1, initial=-np.inf)]


def _check_dtype(source: str, name: str, values: NDArray | StoredMap) -> None:
    """Refuse an array whose dtype is not of the kind :data:`~mpi_lidar.storage.variables.SCAN` declares."""
    dtype = values.stored_dtype if isinstance(values, StoredMap) else np.asarray(values).dtype
    problem = SCAN[name].dtype_problem(dtype)
    if problem is not None:
        fix = "; store it as bool (True where the reference holds)" if name == "reference_mask" else ""
        raise ScanError(f"{source}: {problem}{fix}")


def _parts(values: NDArray | StoredMap) -> Iterator[NDArray]:
    """An array whole, or a stored map a band of rows at a time."""
    if isinstance(values, StoredMap):
        yield from values.c_order_parts()
    else:
        yield values


def from_taps(name: str, frequencies_hz: tuple[float, ...], taps: NDArray, c: float,
              scene: dict[str, object] | None = None, **extras: Unpack[ScanExtras]) -> Scan:
    """A scan from raw taps (F, 4, H, W), demodulated with eq 5-7 (float64 differencing)."""
    taps = np.asarray(taps)
    if taps.ndim != 4 or taps.shape[:2] != (len(frequencies_hz), 4) or not np.issubdtype(taps.dtype, np.floating):
        raise ScanError(f"{name}: taps must be floating point of shape (F={len(frequencies_hz)}, 4, H, W), got "
                        f"{taps.dtype}{taps.shape}")
    moved = np.moveaxis(taps, 1, -1)  # (F, H, W, 4)
    freqs = np.asarray(frequencies_hz)[:, None, None]
    depth, amplitude = demod.depth_and_amplitude(moved, freqs, c)
    return Scan(name=name, frequencies_hz=tuple(frequencies_hz), depth=depth.astype(np.float32),
                amplitude=amplitude.astype(np.float32), taps=taps.astype(np.float32),
                scene={} if scene is None else scene, speed_of_light_m_per_s=float(c), **extras)

