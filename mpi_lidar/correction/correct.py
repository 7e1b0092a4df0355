"""Batch correction of scans: validity mask, a gate that skips pixels needing no correction, inference.

Each pixel gets one flag saying what was done (:class:`Flag`). Invalid pixels (no finite value, no return
above the noise floor, saturated, frequencies that disagree by more than a phase wrap could explain) keep
NaN. Valid pixels whose depth lies outside the range the model was trained on keep their raw depth (trees
do not extrapolate). Valid pixels the gate lets through are corrected by the model; the others keep the
raw depth of the highest frequency, exactly as measured. The default gate, ``geometry``, corrects only
where the scan's own geometry lets another surface send light back (:mod:`mpi_lidar.scans.geometry`); a scan
without geometry falls back to pixel-wise correction of every valid pixel, and its report says so. A model
trained with geometric inputs gets the geometry's coupling and d_AB for each pixel it corrects (computed
even under another gate); on a scan without geometry it corrects nothing, and the report says so.

Per scan the outputs go into ``<out>/<scan name>/`` (``corrected.zarr``, report files, point clouds),
built in a temporary directory and renamed into place, so a scan's outputs are all there or not at all. A
scan already corrected by the same model with the same options (same content hashes) is skipped.
"""

from __future__ import annotations

import glob
import hashlib
import json
import re
import shutil
import time
import uuid
from abc import ABC, abstractmethod
from dataclasses import asdict, dataclass, field
from enum import IntEnum
from functools import lru_cache
from pathlib import Path

import numpy as np
import zarr
from distributed import Client, as_completed
from numpy.typing import NDArray
from scipy import stats

from mpi_lidar.config import Config, SensorConfig, SimulatorConfig
from mpi_lidar.errors import MpiLidarError
from mpi_lidar.learning.features import geometry_inputs
from mpi_lidar.learning.model import CorrectionModel, load_model
from mpi_lidar.physics.moments import MomentSensor
from mpi_lidar.physics.sensor import received_voltage_amplitude
from mpi_lidar.scans import geometry
from mpi_lidar.scans.scan import SCAN_SUFFIX, Scan, read_scan

CORRECTED_SCHEMA = "mpi-lidar/corrected@1"
SAFE_NAME = re.compile(r"^[A-Za-z0-9][A-Za-z0-9._-]{0,127}$")
STAGING_NAME = re.compile(r"^\.[A-Za-z0-9][A-Za-z0-9._-]{0,127}\.(writing|old)-[0-9a-f]{8}$")


class Flag(IntEnum):
    """What was done to a pixel."""

    CORRECTED = 0
    NOT_NEEDED = 1
    NOT_FINITE = 2
    NO_RETURN = 3
    SATURATED = 4
    INCONSISTENT = 5
    OUT_OF_RANGE = 6
    NO_MULTIPATH = 7


INVALID_FLAGS = (Flag.NOT_FINITE, Flag.NO_RETURN, Flag.SATURATED, Flag.INCONSISTENT)


@dataclass(frozen=True)
class CorrectionOptions:
    """Thresholds of the validity mask and the gate; their hash is part of a corrected scan's identity."""

    gate: str = "geometry"
    min_amplitude_sigmas: float = 5.0
    saturation_amplitude_v2: float = 0.7176  # a perfect reflector at 0.5 m; set it from your sensor
    max_depth_spread_m: float = 0.3
    # Zero: near the edge of its prior the model pulls depths inwards, so beyond it raw depth is safer.
    range_tolerance_m: float = 0.0
    consistency_p_value: float = 0.01
    min_multipath_bias_m: float = 0.004
    geometry_block_m: float = geometry.DEFAULT_BLOCK_M
    partner_range_m: float = geometry.DEFAULT_MAX_RANGE_M
    footprint_area_m2: float = geometry.DEFAULT_FOOTPRINT_AREA_M2
    tile_pixels: int = 262_144

    def sha256(self) -> str:
        return hashlib.sha256(json.dumps(asdict(self), sort_keys=True).encode()).hexdigest()


@lru_cache(maxsize=4)
def _noise_model(sensor: SensorConfig, frequencies_hz: tuple[float, ...]) -> MomentSensor:
    # Rounding off: the closed-form moments, which is all a noise prediction needs.
    return MomentSensor(Config(sensor=sensor, frequencies_hz=frequencies_hz,
                               simulator=SimulatorConfig(round_photons=False)))


def noise_floor_v2(sensor: SensorConfig, frequencies_hz: tuple[float, ...]) -> NDArray[np.float64]:
    """Std of each tap quadrature with no light [V^2]: the amplitude of a pixel with no return is of this order."""
    return quadrature_noise_v2(sensor, frequencies_hz, np.zeros((1, len(frequencies_hz))))[0]


def quadrature_noise_v2(sensor: SensorConfig, frequencies_hz: tuple[float, ...], amplitude_v2: NDArray) -> NDArray:
    """Std of a tap quadrature (n, F) [V^2] for single-path light of the measured amplitudes (n, F) [V^2].

    Shot noise grows with the signal, so the depth noise of a pixel is this over its amplitude, times c / 4 pi f.
    """
    model = _noise_model(sensor, tuple(frequencies_hz))
    r = received_voltage_amplitude(np.maximum(amplitude_v2, 0.0), sensor.modulation_contrast,
                                   sensor.demodulation_amplitude_v)
    waveforms = model.waveforms_from_phasors(r, r.astype(np.complex128))
    _, cov = model.waveform_moments(waveforms)
    return np.sqrt(0.5 * (cov[..., 0, 0] + cov[..., 1, 1]))


def validity_flags(raw: NDArray, frequencies_hz: tuple[float, ...], options: CorrectionOptions,
                   sensor: SensorConfig) -> NDArray[np.uint8]:
    """Flag per pixel: NOT_NEEDED for valid pixels (the gate decides later), else the first reason it is invalid."""
    f = len(frequencies_hz)
    depth, amplitude = raw[:, :f], raw[:, f:]
    flags = np.full(raw.shape[0], Flag.NOT_NEEDED, dtype=np.uint8)
    spread = depth.max(axis=1) - depth.min(axis=1) if raw.size else np.zeros(0)  # NaN rows: NOT_FINITE
    floor = options.min_amplitude_sigmas * noise_floor_v2(sensor, tuple(frequencies_hz))
    rules = [
        (Flag.INCONSISTENT, spread > options.max_depth_spread_m),
        (Flag.SATURATED, (amplitude > options.saturation_amplitude_v2).any(axis=1)),
        (Flag.NO_RETURN, (amplitude < floor[None, :]).any(axis=1)),
        (Flag.NOT_FINITE, ~np.isfinite(raw).all(axis=1)),
    ]
    for flag, where in rules:  # later rules win: the most basic reason is reported
        flags[where] = flag
    return flags


class Gate(ABC):
    """Decides which valid pixels need correction.

    Contract: ``needs_correction(raw, frequencies_hz, sensor)`` takes the raw measurements (n, 2F) of valid
    pixels and returns a bool (n,): True where the model should correct. It must be much cheaper than
    inference, since its purpose is to skip work. A gate that looks at the whole scan first overrides
    ``scan_candidates``: a bool (H*W,) of the pixels that may need correction (the others get
    NO_MULTIPATH), or None where it cannot tell; ``uses_geometry`` says whether it wants the geometry.
    """

    name: str
    uses_geometry = False

    def scan_candidates(self, scan: Scan, valid_depth: NDArray) -> NDArray | None:
        """Bool (H*W,) of pixels that may need correction, from the whole scan; None: every pixel may."""
        return None

    @abstractmethod
    def needs_correction(self, raw: NDArray, frequencies_hz: tuple[float, ...], sensor: SensorConfig) -> NDArray:
        """Bool (n,)."""


class CorrectAll(Gate):
    """Every valid pixel is corrected (the paper's pixel-wise correction)."""

    name = "all"

    def needs_correction(self, raw: NDArray, frequencies_hz: tuple[float, ...], sensor: SensorConfig) -> NDArray:
        return np.ones(raw.shape[0], dtype=bool)


class ConsistencyGate(Gate):
    """Corrects pixels whose per-frequency depths disagree by more than their predicted noise allows.

    A pixel with no multipath has the same depth at every frequency up to noise; chi^2 of the depths around
    their inverse-variance mean, with each depth's noise predicted by the moment model at the measured
    amplitude (thermal, TIA and shot noise), follows chi^2(F-1).
    Pixels below the (1 - p) quantile are skipped. At Table I noise and d_AB <= 15 cm the multipath offset
    is almost the same at every frequency, so this test misses most multipath: it is cheap, not sufficient.
    """

    name = "consistency"

    def __init__(self, p_value: float):
        self.p_value = p_value

    def needs_correction(self, raw: NDArray, frequencies_hz: tuple[float, ...], sensor: SensorConfig) -> NDArray:
        f = len(frequencies_hz)
        freqs = np.asarray(frequencies_hz)
        depth = raw[:, :f].astype(np.float64)
        amplitude = np.maximum(raw[:, f:].astype(np.float64), 1e-12)
        metres_per_rad = sensor.speed_of_light_m_per_s / (4 * np.pi * freqs)
        sigma = quadrature_noise_v2(sensor, tuple(frequencies_hz), amplitude) / amplitude * metres_per_rad[None, :]
        weight = sigma**-2
        mean = (weight * depth).sum(1, keepdims=True) / weight.sum(1, keepdims=True)
        chi2 = (weight * (depth - mean) ** 2).sum(1)
        return chi2 > stats.chi2.ppf(1 - self.p_value, df=f - 1)


class GeometryGate(Gate):
    """Corrects only pixels where the scan's geometry allows multipath (:func:`geometry.multipath_potential`).

    A pixel is a candidate where the expected multipath bias of its facing surfaces (white partner, small
    phase) reaches ``min_bias_m`` [m]; flat walls, convex objects and open sky have none. The potential is
    computed from the raw highest-frequency depth of the valid pixels. Scans without geometry (no rays or
    scan grid) get None: every valid pixel is corrected, pixel-wise.
    """

    name = "geometry"
    uses_geometry = True

    def __init__(self, min_bias_m: float, block_m: float, partner_range_m: float, footprint_area_m2: float):
        self.min_bias_m = min_bias_m
        self.block_m = block_m
        self.partner_range_m = partner_range_m
        self.footprint_area_m2 = footprint_area_m2
        self.potential_: geometry.MultipathPotential | None = None

    def potential(self, scan: Scan, valid_depth: NDArray) -> geometry.MultipathPotential | None:
        rays = scan.rays()
        if rays is None:
            return None
        return geometry.multipath_potential(valid_depth.reshape(scan.shape), rays, block_m=self.block_m,
                                            max_range_m=self.partner_range_m,
                                            footprint_area_m2=self.footprint_area_m2)

    def scan_candidates(self, scan: Scan, valid_depth: NDArray) -> NDArray | None:
        self.potential_ = self.potential(scan, valid_depth)
        if self.potential_ is None:
            return None
        return (self.potential_.bias_m >= self.min_bias_m).ravel()

    def needs_correction(self, raw: NDArray, frequencies_hz: tuple[float, ...], sensor: SensorConfig) -> NDArray:
        return np.ones(raw.shape[0], dtype=bool)


NO_GEOMETRY_NOTE = "no scan geometry: the geometry gate fell back to pixel-wise correction of every valid pixel"
NO_GEOMETRY_INPUTS_NOTE = ("no scan geometry: the model needs geometric inputs (coupling, d_AB), so every valid "
                           "pixel keeps its raw depth")


def geometry_gate(options: CorrectionOptions) -> GeometryGate:
    return GeometryGate(options.min_multipath_bias_m, options.geometry_block_m, options.partner_range_m,
                        options.footprint_area_m2)


def make_gate(options: CorrectionOptions) -> Gate:
    gates = {"all": lambda: CorrectAll(), "consistency": lambda: ConsistencyGate(options.consistency_p_value),
             "geometry": lambda: geometry_gate(options)}
    if options.gate not in gates:
        raise MpiLidarError(f"unknown gate {options.gate!r}; choose one of {', '.join(gates)}")
    return gates[options.gate]()


@dataclass(frozen=True)
class Correction:
    """A corrected scan: depth (H, W) [m] (NaN where invalid), flags (H, W), and what it cost.

    ``multipath_bias_m`` (H, W) is the geometry gate's expected multipath bias [m] (None for other gates
    or without geometry); ``gate_s`` the time the gate took [s]; ``notes`` what the report must say.
    """

    depth: NDArray[np.float32]
    flags: NDArray[np.uint8]
    inference_s: float
    total_s: float
    gate_s: float = 0.0
    multipath_bias_m: NDArray[np.float32] | None = None
    notes: tuple[str, ...] = ()

    def counts(self) -> dict[str, int]:
        values, counts = np.unique(self.flags, return_counts=True)
        found = dict(zip(values.tolist(), counts.tolist(), strict=True))
        return {flag.name.lower(): int(found.get(int(flag), 0)) for flag in Flag}


def in_model_range(depth: NDArray, model: CorrectionModel, options: CorrectionOptions) -> NDArray[np.bool_]:
    """Whether measured depths [m] lie in the d_AS range of the model's training prior (plus a tolerance)."""
    low, high = model.card["dataset"]["prior"]["d_as_m"]
    return (depth >= low - options.range_tolerance_m) & (depth <= high + options.range_tolerance_m)


def correct_scan(scan: Scan, model: CorrectionModel, options: CorrectionOptions,
                 sensor: SensorConfig | None = None) -> Correction:
    """Correct one scan in this process, pixel by pixel, in tiles of ``options.tile_pixels``."""
    started = time.perf_counter()
    model.check_compatible(scan.frequencies_hz, model.spec.raw_names, f"scan {scan.name}")
    sensor = sensor or SensorConfig()
    raw = scan.raw_pixels()
    flags = validity_flags(raw, scan.frequencies_hz, options, sensor)
    flags[(flags == Flag.NOT_NEEDED) & ~in_model_range(raw[:, len(scan.frequencies_hz) - 1], model, options)] = (
        Flag.OUT_OF_RANGE)
    gate_started = time.perf_counter()
    gate = make_gate(options)
    top = raw[:, len(scan.frequencies_hz) - 1]
    usable = ~np.isin(flags, [int(f) for f in INVALID_FLAGS])
    usable_depth = np.where(usable, top, np.nan)
    candidates = gate.scan_candidates(scan, usable_depth)
    notes: tuple[str, ...] = ()
    potential = getattr(gate, "potential_", None)
    if model.geometric and potential is None:
        potential = geometry_gate(options).potential(scan, usable_depth)
    if candidates is not None:
        flags[(flags == Flag.NOT_NEEDED) & ~candidates] = Flag.NO_MULTIPATH
    elif gate.uses_geometry and not model.geometric:
        notes = (NO_GEOMETRY_NOTE,)
    valid = np.flatnonzero(flags == Flag.NOT_NEEDED)
    needs = valid[gate.needs_correction(raw[valid], scan.frequencies_hz, sensor)]
    if model.geometric and potential is None:
        needs, notes = needs[:0], (NO_GEOMETRY_INPUTS_NOTE,)
    geometric_inputs = None if potential is None else geometry_inputs(potential.coupling, potential.d_ab_m)
    gate_s = time.perf_counter() - gate_started
    depth = usable_depth.copy()
    inference_started = time.perf_counter()
    for start in range(0, needs.size, options.tile_pixels):
        tile = needs[start:start + options.tile_pixels]
        depth[tile] = model.predict_depth(raw[tile], None if geometric_inputs is None else geometric_inputs[tile])
    inference_s = time.perf_counter() - inference_started
    flags[needs] = Flag.CORRECTED
    h, w = scan.shape
    return Correction(depth.reshape(h, w).astype(np.float32), flags.reshape(h, w), inference_s,
                      time.perf_counter() - started, gate_s,
                      None if potential is None else potential.bias_m.astype(np.float32), notes)


# --- one scan, with its outputs ---------------------------------------------------------------------------


@dataclass(frozen=True)
class ScanOutcome:
    """What happened to one scan of a batch."""

    source: str
    name: str
    status: str  # "corrected", "skipped" (already done) or "failed"
    reason: str = ""
    output: str = ""
    counts: dict[str, int] = field(default_factory=dict)
    metrics: dict[str, dict[str, float]] = field(default_factory=dict)
    seconds: float = 0.0
    notes: tuple[str, ...] = ()


def safe_scan_name(name: str) -> str:
    """The scan's name as an output directory name; anything that could escape the output directory is refused."""
    if not SAFE_NAME.match(name) or ".." in name:
        raise MpiLidarError(f"scan name {name!r} is not a safe directory name (letters, digits, . _ -); "
                            "rename the scan")
    return name


def _already_done(target: Path, scan_sha: str, model_sha: str, options_sha: str) -> bool:
    try:
        attrs = zarr.open_group(store=str(target / "corrected.zarr"), mode="r").attrs
    except Exception:  # no store, or a foreign one: not done
        return False
    return (attrs.get("scan_sha256"), attrs.get("model_sha256"), attrs.get("options_sha256")) == (
        scan_sha, model_sha, options_sha)


def process_scan(source: str | Path, model_dir: str | Path, out_dir: str | Path,
                 options: CorrectionOptions) -> ScanOutcome:
    """Correct one scan and write its outputs; any failure becomes a 'failed' outcome with its reason."""
    started = time.perf_counter()
    source = str(source)
    try:
        return _process_scan(source, Path(model_dir), Path(out_dir), options, started)
    except MpiLidarError as exc:
        return ScanOutcome(source, Path(source).name, "failed", str(exc), seconds=time.perf_counter() - started)
    except (OSError, ValueError, KeyError) as exc:
        return ScanOutcome(source, Path(source).name, "failed", f"{type(exc).__name__}: {exc}",
                           seconds=time.perf_counter() - started)


@lru_cache(maxsize=4)
def _cached_model(model_dir: str) -> CorrectionModel:
    return load_model(model_dir)


def _process_scan(source: str, model_dir: Path, out_dir: Path, options: CorrectionOptions,
                  started: float) -> ScanOutcome:
    from mpi_lidar.reporting.scan_report import scan_metrics, write_scan_outputs

    scan = read_scan(source)
    name = safe_scan_name(scan.name)
    target = out_dir / name
    model = _cached_model(str(model_dir))
    scan_sha, model_sha, options_sha = scan.content_sha256(), model.card["model_sha256"], options.sha256()
    if _already_done(target, scan_sha, model_sha, options_sha):
        return ScanOutcome(source, name, "skipped", "already corrected with this model and options",
                           output=str(target), seconds=time.perf_counter() - started)
    correction = correct_scan(scan, model, options)
    metrics = scan_metrics(scan, correction)
    identity = {"scan_sha256": scan_sha, "model_sha256": model_sha, "options_sha256": options_sha}
    notes = write_scan_outputs(target, scan, correction, metrics, identity, options)
    return ScanOutcome(source, name, "corrected", output=str(target), counts=correction.counts(), metrics=metrics,
                       seconds=time.perf_counter() - started, notes=tuple(notes))


def staged_directory(target: Path) -> Path:
    staging = target.parent / f".{target.name}.writing-{uuid.uuid4().hex[:8]}"
    staging.mkdir(parents=True)
    return staging


def remove_interrupted_staging(out_dir: Path) -> list[Path]:
    """Delete the staging and retired directories a killed batch left in ``out_dir``; they are never outputs.

    Called before a batch starts its scans, so only a batch running at the same time into the same
    directory could lose work to it, and that is not supported.
    """
    leftovers = [p for p in out_dir.glob(".*") if p.is_dir() and STAGING_NAME.match(p.name)]
    for path in leftovers:
        shutil.rmtree(path, ignore_errors=True)
    return leftovers


def swap_into_place(staging: Path, target: Path) -> None:
    """Replace ``target`` with the finished ``staging`` directory; the old outputs go only once the new are in."""
    retired = target.parent / f".{target.name}.old-{uuid.uuid4().hex[:8]}"
    if target.exists():
        target.rename(retired)
    staging.rename(target)
    shutil.rmtree(retired, ignore_errors=True)


# --- a batch ----------------------------------------------------------------------------------------------


def expand_archive(inputs: list[str]) -> list[str]:
    """Scan stores named directly, found in a directory, or matched by a glob; sorted and unique."""
    found: list[str] = []
    for item in inputs:
        path = Path(item)
        if glob.has_magic(item):
            matches = sorted(glob.glob(item))
            if not matches:
                raise MpiLidarError(f"{item} matches no scan; give *{SCAN_SUFFIX} stores, a directory or a glob")
            found += matches
        elif path.name.endswith(SCAN_SUFFIX) or (path.is_dir() and (path / "zarr.json").exists()):
            found.append(str(path))
        elif path.is_dir():
            found += sorted(str(p) for p in path.glob(f"*{SCAN_SUFFIX}"))
        else:
            raise MpiLidarError(f"{item} is not a scan store or a directory of *{SCAN_SUFFIX} stores")
    return sorted(dict.fromkeys(found))


def correct_archive(inputs: list[str], model_dir: str | Path, out_dir: str | Path, options: CorrectionOptions,
                    client: Client | None = None, on_scan=None) -> list[ScanOutcome]:
    """Correct every scan, one task per scan on Dask (or in this process); a bad scan fails alone."""
    load_model(model_dir)  # a broken model fails the whole batch at once, with one clear line
    make_gate(options)
    out_dir = Path(out_dir)
    try:
        out_dir.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise MpiLidarError(f"cannot create output directory {out_dir}: {exc.strerror or exc}") from None
    sources = expand_archive(inputs)
    remove_interrupted_staging(out_dir)
    outcomes: list[ScanOutcome] = []
    if client is None:
        for source in sources:
            outcomes.append(process_scan(source, model_dir, out_dir, options))
            if on_scan:
                on_scan(outcomes[-1])
    else:
        futures = [client.submit(process_scan, s, str(model_dir), str(out_dir), options, pure=False) for s in sources]
        for future in as_completed(futures):
            outcomes.append(future.result())
            if on_scan:
                on_scan(outcomes[-1])
    return sorted(outcomes, key=lambda o: o.source)
