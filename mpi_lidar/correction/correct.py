"""Batch correction of scans: validity mask, a gate that skips pixels needing no correction, inference.

Each pixel gets one flag saying what was done (:class:`Flag`). Invalid pixels (no finite value, no return
above the noise floor, saturated, frequencies that disagree by more than a phase wrap could explain) keep
NaN. Valid pixels whose depth lies beyond the far end of the range the model was trained on keep their raw
depth (trees do not extrapolate, and near that end the model pulls depths inwards), as do those more than
15 % nearer than its near end (``CorrectionOptions.near_range_fraction``: multipath only lengthens a path,
so a depth measured near is truly near, and just below its range the model corrects as well as inside
it). Valid pixels the gate lets through are corrected by the model; the others keep the raw depth of the
highest frequency, exactly as measured. The default gate, ``geometry``, corrects only
where the scan's own geometry lets another surface send light back (:mod:`mpi_lidar.scans.geometry`); a scan
without geometry falls back to pixel-wise correction of every valid pixel, and its report says so. A model
trained with geometric inputs gets the geometry's rho_ABA and d_AB estimates for each pixel it corrects (computed
even under another gate); on a scan without geometry it corrects nothing, and the report says so.

Per scan the outputs go into ``<out>/<scan name>/`` (``corrected.zarr``, report files, point clouds),
built in a temporary directory and renamed into place, so a scan's outputs are all there or not at all. A
scan already corrected by the same model with the same options (same content hashes) is skipped.
"""
from __future__ import annotations

import time
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field, replace
from typing import cast

import numpy as np
from numpy.typing import NDArray

from mpi_lidar.config import SensorConfig
from mpi_lidar.correction.amplitude_in_v2 import AmplitudeInV2
from mpi_lidar.correction.amplitude_unit import V2_TOLERANCE, AmplitudeUnit, measure_amplitude_unit, reads_as_v2
from mpi_lidar.correction.footprint import FootprintEstimate, PlaneModelInputs
from mpi_lidar.correction.gates import Gate, make_gate
from mpi_lidar.correction.options import (
    AUTO,
    INVALID_FLAGS,
    Baseline,
    CorrectionOptions,
    Estimate,
    Flag,
    UnservedReason,
)
from mpi_lidar.correction.outcome import Unserved
from mpi_lidar.correction.scene import SceneGeometry, analyse_geometry
from mpi_lidar.correction.unwrapped_depth import UnwrappedDepth
from mpi_lidar.correction.validity import (
    UNUSABLE_FLAGS,
    depth_rules_only,
    unwrapped_rows,
    usable_depth_of,
    validity_flags,
)
from mpi_lidar.learning.error_model import corrected_sigma_m
from mpi_lidar.learning.features import geometry_inputs
from mpi_lidar.learning.model import CorrectionModel, ModelCard
from mpi_lidar.physics.noise import fused_depths
from mpi_lidar.physics.window import window_corrections_m
from mpi_lidar.scans.scan import Scan
from mpi_lidar.scans.stored_map import StoredMap
from mpi_lidar.threads import on_cores_by_rows

# Rows of a tile's per-pixel work (validity, the model's inputs) that one thread takes at least: NumPy
# releases the GIL in its loops, so a tile's rows are split among the cores, each row computed as alone.
PARALLEL_MIN_ROWS = 16_384
# A scene saturates where it is near and bright; amplitudes in a unit larger than the model's saturate nearly
# everywhere. Above this share of the pixels with a measurement, a scan is unserved for its amplitude units.
SATURATED_UNITS_SHARE = 0.9
# Above this share of the pixels with a measurement ambiguous in range, the scan is unserved for it.
AMBIGUOUS_SHARE = 0.5


@dataclass(frozen=True)
class Correction:
    """A corrected scan: depth (H, W) [m] (NaN where invalid), flags (H, W), and what it cost.

    ``multipath_bias_m`` (H, W) is the scene geometry's expected multipath bias [m] (None where the geometry
    was not analysed or the scan has none); ``gate_s`` the time the scene geometry and the gate took [s];
    ``notes`` what the report must say;
    ``cpu_s`` the CPU seconds of this process (all threads) per stage: validity, gate, inference (the model's
    features and its prediction) [s]; ``calibration`` the scan's own footprint estimate where the footprint
    was "auto" and the geometry was analysed (None otherwise); ``unserved`` why the model could not serve the
    scan (None where it could); ``measured_depth`` (H, W) the highest frequency's depth as measured [m],
    unwrapped into one range where the scan's depths were wrapped (as measured where the range is ambiguous),
    which is what correction compares with; ``unwrap_confidence`` (H, W) the unwrapping's confidence [1] (None
    for a scan whose depths came unwrapped); ``estimate`` (H, W) which estimate each depth is
    (:class:`~mpi_lidar.correction.options.Estimate`); ``uncertainty_m`` (H, W) each depth's 1-sigma
    uncertainty [m] (NaN where it has none); ``frequency_offsets_m`` the frequencies' depth offsets relative to the
    highest [m] that the fused depths had removed (None: none), after the integration window's leakage where
    ``window_leakage_removed`` (:func:`window_corrections_m`); ``amplitude_units_per_v2`` the scanner's amplitude
    unit per V^2 that the scan's amplitudes were divided by (1: read as V^2), which outputs showing the
    amplitudes in V^2 divide them by too.
    """

    depth: NDArray[np.float32]
    flags: NDArray[np.uint8]
    inference_s: float
    total_s: float
    gate_s: float = 0.0
    multipath_bias_m: NDArray[np.float32] | None = None
    notes: tuple[str, ...] = ()
    cpu_s: dict[str, float] = field(default_factory=dict)
    calibration: FootprintEstimate | None = None
    unserved: Unserved | None = None
    measured_depth: NDArray[np.float32] | None = None
    unwrap_confidence: NDArray[np.float32] | None = None
    estimate: NDArray[np.uint8] | None = None
    uncertainty_m: NDArray[np.float32] | None = None
    frequency_offsets_m: tuple[float, ...] | None = None
    amplitude_units_per_v2: float = 1.0
    window_leakage_removed: bool = False

    def counts(self) -> dict[str, int]:
        found = code_counts(self.flags, len(Flag))
        return {flag.name.lower(): int(found[int(flag)]) for flag in Flag}

    def estimate_counts(self) -> dict[str, int]:
        """Pixels per estimate (:class:`~mpi_lidar.correction.options.Estimate`): none, measured, fused, corrected."""
        if self.estimate is None:
            return {}
        found = code_counts(self.estimate, len(Estimate))
        return {estimate.name.lower(): int(found[int(estimate)]) for estimate in Estimate}

    def uncertainty_summary(self) -> dict[str, float]:
        """Median and 95th percentile of the depths' 1-sigma uncertainty [m] over the pixels that have one."""
        if self.uncertainty_m is None or not np.isfinite(self.uncertainty_m).any():
            return {}
        median, high = np.nanpercentile(self.uncertainty_m, [50, 95])
        return {"median_m": float(median), "p95_m": float(high)}


# Codes counted at a time (:func:`code_counts`): np.bincount widens its input to intp first, eight bytes a pixel.
COUNT_CHUNK_PIXELS = 2**20


def code_counts(codes: NDArray[np.uint8], length: int) -> NDArray[np.intp]:
    """How many of ``codes`` (any shape) take each value below ``length`` (length,), a chunk of
    ``COUNT_CHUNK_PIXELS`` at a time, so that a whole scan is never widened to intp at once."""
    flat = codes.reshape(-1)
    found = np.zeros(length, dtype=np.intp)
    for start in range(0, flat.size, COUNT_CHUNK_PIXELS):
        found += np.bincount(flat[start:start + COUNT_CHUNK_PIXELS], minlength=length)[:length]
    return found


def in_model_range(depth: NDArray, model: CorrectionModel, options: CorrectionOptions) -> NDArray[np.bool_]:
    """Whether measured depths [m] lie in the d_AS range of the model's training prior (plus a tolerance)."""
    return in_depth_range(depth, model.card.dataset.prior.d_as_m, options)


def in_depth_range(depth: NDArray, d_as_m: tuple[float, float], options: CorrectionOptions) -> NDArray[np.bool_]:
    """Whether measured depths [m] lie in the range ``d_as_m`` [m], its near end moved in by
    ``options.near_range_fraction`` of itself, both ends widened by ``options.range_tolerance_m``."""
    low, high = d_as_m
    nearest = low * (1.0 - options.near_range_fraction) - options.range_tolerance_m
    return (depth >= nearest) & (depth <= high + options.range_tolerance_m)


def correct_scan(scan: Scan, model: CorrectionModel, options: CorrectionOptions | None = None,
                 sensor: SensorConfig | None = None) -> Correction:
    """Correct one scan in this process, in tiles of whole rows of about ``options.tile_pixels`` pixels.

    The stages: validity (:func:`_validity_pass`) -> scene geometry (:func:`analyse_geometry`, where the gate or
    the model needs it) -> the gate's decision (:func:`_gate`) -> the model (:func:`_predict`). Everything per
    pixel (validity mask, model range, a pixel-wise gate, geometric inputs, inference) runs tile by tile, so its
    working memory is that of one tile whatever the scan's size; the scene geometry runs between the two passes,
    itself in tiles of whole blocks (its planes) and bands of rows (its potential), with only its facing pairs
    over the whole scan. ``scan`` may keep its maps in the store
    (:class:`mpi_lidar.scans.stored_map.StoredMap`). Every pixel gets exactly the value it gets from the whole scan
    in memory at once (tests/correction/test_tiling.py, tests/scans/test_stored_maps.py). ``options`` None: the
    defaults.
    """
    started = time.perf_counter()
    options = options or CorrectionOptions()
    clock = _StageClock()
    model.check_compatible(scan.frequencies_hz, model.spec.raw_names, f"scan {scan.name}")
    sensor = sensor or SensorConfig()
    tiles = scan_tiles(scan, options.tile_pixels)
    unit_note: tuple[str, ...] = ()
    if options.amplitude_scale == AUTO:
        with clock("validity"):
            unit = measure_amplitude_unit(scan, sensor, noise_scale=options.noise_scale,
                                          max_depth_spread_m=options.max_depth_spread_m)
        if not unit.significant:
            return _left_as_measured(scan, *_validity_pass(scan, depth_rules_only(options), sensor, tiles), unit,
                                     started)
        unit_note = (unit_note_of(unit),)
        units_per_v2 = 1.0 if reads_as_v2(unit) else unit.amplitude_scale
    else:
        units_per_v2 = float(options.amplitude_scale)
    if units_per_v2 != 1.0:  # the scanner's unit to V^2, once, in memory
        scan = _in_v2(scan, units_per_v2)
    with clock("validity"):
        flags, usable_depth, measured = _validity_pass(scan, options, sensor, tiles)
        if measured.moved:  # some depths wrapped: every later stage reads them unwrapped
            scan = _unwrapped_scan(scan, *measured.take_moved())
    gate_started = time.perf_counter()
    with clock("gate"):
        gate = make_gate(options)
        scene = None
        if gate.uses_geometry or model.geometric:
            scene = analyse_geometry(scan, usable_depth, options, sensor, with_model_inputs=model.geometric)
        notes = _gate(flags, gate, scene)
        _range_rule(flags, usable_depth, model, options)
    gate_s = time.perf_counter() - gate_started
    inputs = None if scene is None else scene.model_inputs
    bias_m = None if scene is None else scene.bias_m
    calibration = None if scene is None else scene.footprint
    predict = not (model.geometric and (scene is None or not scene.has_geometry))
    del scene  # its masks are in the flags now
    depth = usable_depth  # the scene geometry is done with it: filled in place, no copy
    ambiguous = np.flatnonzero(flags == Flag.AMBIGUOUS)  # indices, not a mask of the whole scan kept to the end
    depth[ambiguous] = measured.depth[ambiguous]  # a range that cannot be told: as measured
    inference_s = 0.0
    if predict:
        reach = model.card.dataset.prior.multipath_reach()
        gate_s, inference_s, beyond = _predict(scan, model, sensor, tiles, gate, flags, depth, inputs, clock, gate_s,
                                               reach)
        notes += _beyond_prior_note(beyond, reach)
    del inputs  # the blocks and planes of the geometric inputs: the model was their last reader
    with clock("validity"):
        offsets, offset_notes = _frequency_offsets(measured, flags, bias_m, options)
        estimate, uncertainty = _estimates(scan, sensor, tiles, flags, depth, measured.depth, options, offsets,
                                           calibration, None if bias_m is None else bias_m.reshape(-1), model.card)
    notes += offset_notes
    h, w = scan.shape
    unserved = unserved_reason(flags, model, options, served=predict)
    return Correction(depth.reshape(h, w), flags.reshape(h, w), inference_s, time.perf_counter() - started, gate_s,
                      bias_m, unit_note + notes, clock.seconds, calibration, unserved, measured.depth.reshape(h, w),
                      None if measured.confidence is None else measured.confidence.reshape(h, w),
                      estimate.reshape(h, w), uncertainty.reshape(h, w),
                      None if offsets.offsets_m is None else tuple(float(o) for o in offsets.offsets_m),
                      units_per_v2, offsets.window)


# Valid pixels the model leaves alone, whose depth is the baseline's: fused where the frequencies agree.
BASELINE_FLAGS = (Flag.NOT_NEEDED, Flag.NO_MULTIPATH, Flag.UNCALIBRATED, Flag.OUT_OF_RANGE)


@dataclass(frozen=True)
class _Offsets:
    """What the fused depths remove from each frequency's depth: the integration window's leakage (``window``,
    :func:`window_corrections_m`) and then the frequencies' offsets relative to the highest (F,) [m] (None: none)."""

    offsets_m: NDArray | None = None
    window: bool = False


def _frequency_offsets(measured: _Measured, flags: NDArray[np.uint8], bias_m: NDArray | None,
                       options: CorrectionOptions) -> tuple[_Offsets, tuple[str, ...]]:
    """What the fused depths remove (:class:`_Offsets`), and what the report says of it: the options' (a sensor
    profile's) offsets where they give them, else the scan's own, measured on its valid pixels that the scene
    geometry expects free of multipath (``bias_m`` (H, W) [m]); nothing where it has too few such pixels or no
    geometry.

    The scan also says whether its sensor has the default window's leakage: the leakage is removed where that
    leaves the frequencies' measured offsets smaller (in sum of squares) than it finds them. A sensor with it
    shows the leakage's differences between frequencies as offsets; removing it where a sensor has none would
    show them, reversed.
    """
    if Baseline(options.baseline) == Baseline.RAW:
        return _Offsets(), ()  # nothing is fused
    if options.frequency_offsets_m is not None:  # a profile's, measured with the leakage removed or not
        return _Offsets(np.asarray(options.frequency_offsets_m, dtype=np.float64),
                        bool(options.window_leakage_removed)), ()
    if bias_m is None:
        return _Offsets(), ("frequency offsets: not measured (no scene geometry to find pixels free of multipath); "
                            "none removed from the fused depths",)
    stride = measured.offsets.stride  # only the sampled pixels: no mask of the whole scan
    quiet = np.isin(flags[::stride], [int(flag) for flag in BASELINE_FLAGS])
    quiet &= bias_m.reshape(-1)[::stride] <= QUIET_BIAS_M
    as_measured = measured.offsets.offsets_m(quiet, window=False)
    if as_measured is None:
        return _Offsets(), (f"frequency offsets: not measured (fewer than {MIN_OFFSET_PIXELS} sampled pixels free "
                            "of multipath); none removed from the fused depths",)
    windowed = measured.offsets.offsets_m(quiet, window=True)
    assert windowed is not None  # the same pixels
    window = bool(np.sum(windowed**2) < np.sum(as_measured**2))
    offsets, other = (windowed, as_measured) if window else (as_measured, windowed)
    listed, other_listed = offsets_mm(offsets), offsets_mm(other)
    leakage = "removed first" if window else "left in"
    return _Offsets(offsets, window), (
        f"frequency offsets: {listed} mm relative to the highest frequency, measured on the pixels free of "
        f"multipath, removed from the fused depths; the integration window's leakage {leakage} (the offsets "
        f"would be {other_listed} mm otherwise)",)


def offsets_mm(offsets_m: NDArray | tuple[float, ...]) -> str:
    """The frequencies' offsets [m] as a report lists them: millimetres, signed, comma-separated."""
    return ", ".join(f"{1e3 * o:+.3f}" for o in offsets_m)


def _estimates(scan: Scan, sensor: SensorConfig, tiles: list[slice], flags: NDArray[np.uint8],
               depth: NDArray[np.float32], measured_depth: NDArray[np.float32], options: CorrectionOptions,
               offsets: _Offsets, footprint: FootprintEstimate | None, bias_m: NDArray | None,
               card: ModelCard) -> tuple[NDArray[np.uint8], NDArray[np.float32]]:
    """Which estimate each pixel's depth is (:class:`Estimate`) and its 1-sigma uncertainty [m], (H*W,) each, tile
    by tile; the baseline's pixels take the fused depth (:func:`fused_depths`, ``offsets`` removed) into
    ``depth`` in place where ``options.baseline`` is fused and their frequencies agree within noise.

    Uncertainty: the fused depth's sd under the noise model; the measured depth's sd, times the frequencies' Birge
    ratio where they disagree beyond their noise (multipath or a flying pixel); for both, combined
    with the multipath bias the scene geometry expects (``bias_m`` (H*W,) [m], below the gate's threshold, else
    the pixel would be corrected); a corrected depth's from the model's own error as its ``card`` states it and the
    share of its correction that the footprint estimate's uncertainty leaves open (:func:`corrected_uncertainty_m`).
    NaN where there is no depth, and where the range is ambiguous (its wrap count, metres, is not known).
    """
    fuse = Baseline(options.baseline) == Baseline.FUSED
    estimate = np.full(flags.size, Estimate.NONE, dtype=np.uint8)
    uncertainty = np.full(flags.size, np.nan, dtype=np.float32)
    known = [int(flag) for flag in (*BASELINE_FLAGS, Flag.CORRECTED)]
    for pixels, raw in _raw_tiles(scan, tiles):
        def estimate_rows(rows: slice, start: int = pixels.start, raw: NDArray = raw) -> None:
            where = slice(start + rows.start, start + rows.stop)
            tile_flags = flags[where]
            estimate[where] = np.where(np.isin(tile_flags, [int(flag) for flag in INVALID_FLAGS]), Estimate.NONE,
                                       Estimate.MEASURED)
            present = np.flatnonzero(np.isin(tile_flags, known))
            with np.errstate(invalid="ignore", divide="ignore", over="ignore"):
                fused = fused_depths(raw[rows][present], scan.frequencies_hz, sensor,
                                     noise_scale=options.noise_scale, offsets_m=offsets.offsets_m,
                                     window=offsets.window)
            # Frequencies that disagree beyond their noise (multipath, a flying pixel) widen the measured sd by
            # their Birge ratio.
            measured_sigma = fused.top_sigma_m * np.where(fused.consistent, 1.0, fused.birge_ratio)
            index = where.start + present
            corrected = tile_flags[present] == Flag.CORRECTED
            expected = np.zeros(present.size) if bias_m is None else bias_m[index].astype(np.float64)
            sigma = np.array(measured_sigma)
            if fuse:
                take = ~corrected & fused.consistent
                depth[index[take]] = fused.depth_m[take]
                sigma[take] = fused.sigma_m[take]
                estimate[index[take]] = Estimate.FUSED
            # A pixel left alone keeps the multipath bias its scene geometry expects (below the gate's threshold).
            uncertainty[index] = np.hypot(sigma, expected)
            uncertainty[index[corrected]] = corrected_uncertainty_m(
                card, measured_sigma[corrected], fused.sigma_m[corrected],
                depth[index[corrected]] - measured_depth[index[corrected]], footprint)
            estimate[index[corrected]] = Estimate.CORRECTED

        on_cores_by_rows(estimate_rows, raw.shape[0], PARALLEL_MIN_ROWS)
    return estimate, uncertainty


def corrected_uncertainty_m(card: ModelCard, measured_sigma_m: NDArray, fused_sigma_m: NDArray,
                            correction_m: NDArray, footprint: FootprintEstimate | None) -> NDArray[np.float32]:
    """1-sigma uncertainty [m] of depths corrected by the model of ``card``, from the measured depth's sd (n,) [m],
    the fused depth's sd under the noise model (n,) [m] and the correction (n,) [m].

    With the card's uncertainty model (:mod:`mpi_lidar.learning.error_model`): the model's error as fitted on the
    validation rows of its training (68 % of their errors within it), from the fused sd and the size of the
    correction, combined with the share of the correction that the footprint estimate's relative uncertainty leaves
    open (:func:`footprint_left_open`). A card without one (written before it was fitted): the measured sd and
    that share, without the model's own error.
    """
    relative = footprint_left_open(card, footprint)
    if card.uncertainty_model is None:
        base_m = np.asarray(measured_sigma_m, dtype=np.float64)
    else:
        base_m = corrected_sigma_m(card.uncertainty_model, fused_sigma_m, correction_m)
    return np.hypot(base_m, relative * np.asarray(correction_m, dtype=np.float64)).astype(np.float32)


def footprint_left_open(card: ModelCard, footprint: FootprintEstimate | None) -> float:
    """The footprint estimate's relative uncertainty [1] that a corrected depth's uncertainty must add, as a share
    of the correction (the multipath bias scales with the footprint; a given footprint, ``footprint`` None, adds
    nothing).

    A card with an uncertainty model has the validation rows' errors in it, and those rows' geometric inputs
    carried an estimation error of their coupling (``geometry_error_model``): only a footprint less certain than
    that adds the excess (in quadrature); a model without geometric inputs does not read the footprint, which then
    adds nothing. A card without an uncertainty model: the whole relative uncertainty.
    """
    if footprint is None or not np.isfinite(footprint.area_m2) or footprint.area_m2 <= 0:
        return 0.0
    relative = float(footprint.sigma_m2 / footprint.area_m2)
    if card.uncertainty_model is None:
        return relative
    if not card.geometric:
        return 0.0
    trained = 0.0 if card.geometry_error_model is None else card.geometry_error_model.coupling_log_sd
    return float(np.sqrt(max(relative**2 - trained**2, 0.0)))


def _in_v2(scan: Scan, units_per_v2: float) -> Scan:
    """The scan with its amplitudes divided by the scanner's unit per V^2 as they are read (no copy of the maps)."""
    return replace(scan, amplitude=cast("NDArray[np.float32]", AmplitudeInV2(scan.amplitude, units_per_v2)))


def unit_note_of(unit: AmplitudeUnit) -> str:
    """What a report says of a scan's own amplitude unit."""
    if not unit.significant:
        return f"amplitude unit auto: not measured ({unit.reason}); every pixel left as measured"
    measured = (f"amplitude unit auto: {unit.amplitude_scale:.4g} +- {unit.relative_sigma * unit.amplitude_scale:.2g}"
                f" per V^2 from the scatter of the frequencies on {unit.pixels:,} pixels")
    if reads_as_v2(unit):
        return f"{measured}, within a factor {V2_TOLERANCE:g} of V^2: read as V^2"
    return f"{measured}; amplitudes divided by it"


def _left_as_measured(scan: Scan, flags: NDArray[np.uint8], usable_depth: NDArray[np.float32], measured: _Measured,
                      unit: AmplitudeUnit, started: float) -> Correction:
    """A scan whose amplitude unit could not be measured: validity from the depths alone (``flags``,
    ``usable_depth``, ``measured`` of :func:`_validity_pass`), every valid pixel as measured (flag uncalibrated),
    the scan unserved for its amplitude unit."""
    flags[flags == Flag.NOT_NEEDED] = Flag.UNCALIBRATED
    depth = np.where(flags == Flag.AMBIGUOUS, measured.depth, usable_depth).astype(np.float32)
    h, w = scan.shape
    why = Unserved(UnservedReason.AMPLITUDE_UNITS,
                   f"the scan's amplitude unit could not be measured ({unit.reason}): give it "
                   "(mpi-lidar correct --amplitude-scale, or a profile from mpi-lidar calibrate: --sensor)")
    return Correction(depth.reshape(h, w), flags.reshape(h, w), 0.0, time.perf_counter() - started,
                      notes=(unit_note_of(unit),), unserved=why, measured_depth=measured.depth.reshape(h, w),
                      unwrap_confidence=None if measured.confidence is None else measured.confidence.reshape(h, w),
                      estimate=np.where(np.isin(flags, [int(flag) for flag in INVALID_FLAGS]), Estimate.NONE,
                                        Estimate.MEASURED).astype(np.uint8).reshape(h, w),
                      # The noise model needs the amplitudes' unit: no uncertainty without it.
                      uncertainty_m=np.full((h, w), np.nan, dtype=np.float32))


def _range_rule(flags: NDArray[np.uint8], usable_depth: NDArray[np.float32], model: CorrectionModel,
                options: CorrectionOptions) -> None:
    """OUT_OF_RANGE, in place, for the pixels still to correct after the gate (NOT_NEEDED) whose depth lies
    outside the model's range (:func:`in_model_range`). After the gate, so that a pixel out of range that
    needs no correction says so (NO_MULTIPATH), and OUT_OF_RANGE counts only what the model failed to serve."""
    candidates = np.flatnonzero(flags == Flag.NOT_NEEDED)
    outside = ~in_model_range(usable_depth[candidates], model, options)
    flags[candidates[outside]] = Flag.OUT_OF_RANGE


def unserved_reason(flags: NDArray[np.uint8], model: CorrectionModel, options: CorrectionOptions,
                    served: bool = True) -> Unserved | None:
    """Why ``model`` could not serve a scan of these ``flags`` (H*W,), or None where it could.

    ``served`` False: the model takes geometric inputs and the scan has none. Saturation in more than
    :data:`SATURATED_UNITS_SHARE` of the measured pixels reads as amplitudes in another unit; no corrected pixel while
    some pixels that may need correction were out of the model's range, as a range it was not trained for.
    """
    counts = code_counts(flags, len(Flag))
    measured = max(int(flags.size - counts[Flag.NOT_FINITE]), 1)
    low, high = model.card.dataset.prior.d_as_m
    if counts[Flag.SATURATED] / measured > SATURATED_UNITS_SHARE:
        return Unserved(UnservedReason.AMPLITUDE_UNITS,
                        f"{100 * counts[Flag.SATURATED] / measured:.0f} % of the pixels read as saturated (above "
                        f"{options.saturation_amplitude_v2:g} V^2): the amplitudes are likely in another unit; "
                        "give the scanner's unit per V^2 (mpi-lidar correct --amplitude-scale, or a profile from "
                        "mpi-lidar calibrate: --sensor sensor.toml)")
    if not served:
        return Unserved(UnservedReason.NO_GEOMETRY,
                        "the model takes geometric inputs and the scan has no geometry: import the scan with its "
                        "azimuth and elevation (mpi-lidar import-scan), or train a model without them "
                        "(mpi-lidar train --no-geometric)")
    if counts[Flag.AMBIGUOUS] / measured > AMBIGUOUS_SHARE:
        return Unserved(UnservedReason.AMBIGUOUS_RANGE,
                        f"{100 * counts[Flag.AMBIGUOUS] / measured:.0f} % of the pixels have an ambiguous range: "
                        "their frequencies' wrap counts cannot be told apart at their noise; if the scanner "
                        "unwrapped its depths already, import them so (mpi-lidar import-scan --depths unwrapped)")
    if counts[Flag.CORRECTED] == 0 and counts[Flag.OUT_OF_RANGE] > 0:
        return Unserved(UnservedReason.OUT_OF_RANGE,
                        f"{counts[Flag.OUT_OF_RANGE]:,} pixels that may need correction lie outside the model's "
                        f"range ({low:g}-{high:g} m) and none inside it: train a model for the scan's range "
                        "(mpi-lidar pipeline --config with prior.d_as_m set)")
    return None


@dataclass
class _Measured:
    """The highest frequency's depth of every pixel as measured (H*W,) [m], unwrapped into one range where the
    scan's depths were wrapped and the unwrapping is certain, the unwrapping's confidence (H*W,) [1] (None
    for a scan whose depths came unwrapped), whether any depth took a wrap count (``moved``), and a sample of the
    frequencies' depths less the highest one's (:class:`_OffsetSample`)."""

    depth: NDArray[np.float32]
    confidence: NDArray[np.float32] | None
    offsets: _OffsetSample
    # (flat pixel indices (k,), their unwrapped depths (k, F) [m]) of the pixels whose depths took a wrap count,
    # a part per band of rows: the scan's depths are unwrapped from them without a second search.
    moved_pixels: list[tuple[NDArray[np.intp], NDArray[np.float32]]] = field(default_factory=list)

    @property
    def moved(self) -> bool:
        """Whether any depth took a wrap count."""
        return bool(self.moved_pixels)

    def take_moved(self) -> tuple[NDArray[np.intp], NDArray[np.float32]]:
        """The flat indices (k,) of the pixels whose depths took a wrap count, ascending, and their unwrapped
        depths (k, F) [m], in one array each; the parts they came in are let go."""
        parts = sorted(self.moved_pixels, key=lambda part: int(part[0][0]))  # each part ascending, disjoint
        self.moved_pixels = []
        return np.concatenate([pixels for pixels, _ in parts]), np.concatenate([depths for _, depths in parts])


# The frequencies' relative offsets are measured on at most about this many pixels, evenly spaced: beyond that
# the median's noise is far below the offsets, a few tenths of a millimetre.
OFFSET_SAMPLE_PIXELS = 100_000
# ... and only with at least this many pixels free of multipath (else none is removed).
MIN_OFFSET_PIXELS = 500
# A pixel is free of multipath for the offsets where the scene geometry expects a bias below this [m].
QUIET_BIAS_M = 2e-5


@dataclass
class _OffsetSample:
    """Every ``stride``-th pixel's depth at each frequency less the highest frequency's (K, F) [m] (NaN where
    invalid), as measured and with the integration window's leakage removed from each
    (:func:`window_corrections_m`): what the frequencies' relative offsets are measured from, once the scene says
    which pixels are free of multipath."""

    stride: int
    differences: NDArray[np.float32]
    window_differences: NDArray[np.float32]

    @classmethod
    def empty(cls, pixels: int, frequencies: int) -> _OffsetSample:
        stride = max(1, -(-pixels // OFFSET_SAMPLE_PIXELS))
        shape = (-(-pixels // stride), frequencies)
        return cls(stride, np.full(shape, np.nan, dtype=np.float32), np.full(shape, np.nan, dtype=np.float32))

    def fill(self, start: int, rows: NDArray, usable: NDArray, frequencies_hz: tuple[float, ...],
             sensor: SensorConfig) -> None:
        """The sampled pixels among the rows (n, 2F) of unwrapped raw measurements that start at pixel ``start``
        (``usable`` (n,): valid, of a known range)."""
        first = -(-start // self.stride) * self.stride - start  # the first sampled pixel in these rows
        picked = np.arange(first, rows.shape[0], self.stride)
        f = self.differences.shape[1]
        depth = rows[picked, :f]
        windowed = depth + window_corrections_m(depth, rows[picked, f:], frequencies_hz, sensor)
        at = (start + picked) // self.stride
        for differences, depths in ((self.differences, depth), (self.window_differences, windowed)):
            differences[at] = np.where(usable[picked, None], depths - depths[:, f - 1:f], np.nan)

    def offsets_m(self, quiet: NDArray[np.bool_], window: bool) -> NDArray[np.float64] | None:
        """The median difference of each frequency (F,) [m] over the sampled pixels that are ``quiet`` (K,: of
        every ``stride``-th pixel), with the window's leakage removed first or not, or None with fewer than
        ``MIN_OFFSET_PIXELS`` of them."""
        differences = self.window_differences if window else self.differences
        taken = quiet & np.isfinite(differences).all(1)
        if taken.sum() < MIN_OFFSET_PIXELS:
            return None
        return np.median(differences[taken].astype(np.float64), axis=0)


def _validity_pass(scan: Scan, options: CorrectionOptions, sensor: SensorConfig, tiles: list[slice],
                   ) -> tuple[NDArray[np.uint8], NDArray[np.float32], _Measured]:
    """Unwrapping and validity of every pixel, tile by tile: the flags (H*W,) (NOT_NEEDED where valid), the
    highest-frequency depth of the usable pixels (H*W,) [m] (NaN elsewhere) and the measured depth."""
    f = len(scan.frequencies_hz)
    flags = np.empty(scan.shape[0] * scan.shape[1], dtype=np.uint8)
    usable_depth = np.empty(flags.size, dtype=np.float32)
    measured = _Measured(np.empty(flags.size, dtype=np.float32),
                         np.empty(flags.size, dtype=np.float32) if scan.depth_wrapped else None,
                         _OffsetSample.empty(flags.size, f))
    for pixels, raw in _raw_tiles(scan, tiles):
        def check(rows: slice, start: int = pixels.start, raw: NDArray = raw) -> None:
            part, confidence = _unwrapped(scan, raw[rows], sensor)
            part_flags = validity_flags(part, scan.frequencies_hz, options, sensor, confidence)
            where = slice(start + rows.start, start + rows.stop)
            flags[where] = part_flags
            measured.offsets.fill(where.start, part, ~np.isin(part_flags, [int(flag) for flag in UNUSABLE_FLAGS]),
                                  scan.frequencies_hz, sensor)
            usable_depth[where] = usable_depth_of(part, part_flags)
            measured.depth[where] = np.where(part_flags == Flag.AMBIGUOUS, raw[rows, f - 1], part[:, f - 1])
            if measured.confidence is not None and confidence is not None:
                measured.confidence[where] = confidence
                # Bit by bit: a row that took no wrap count keeps its bytes (NaN included).
                moved = np.flatnonzero((part[:, :f].view(np.uint32) != raw[rows, :f].view(np.uint32)).any(1))
                if moved.size:  # list.append is atomic: the threads' parts need no lock
                    measured.moved_pixels.append((where.start + moved, part[moved, :f].copy()))

        on_cores_by_rows(check, raw.shape[0], PARALLEL_MIN_ROWS)
    return flags, usable_depth, measured


def _unwrapped(scan: Scan, raw: NDArray[np.float32], sensor: SensorConfig,
               ) -> tuple[NDArray[np.float32], NDArray[np.float64] | None]:
    """Raw rows of the scan with their depths in one range (:func:`unwrapped_rows`) where the scan's depths are
    wrapped, and the unwrapping's confidence; the rows as they are (and None) where they came unwrapped."""
    if not scan.depth_wrapped:
        return raw, None
    return unwrapped_rows(raw, scan.frequencies_hz, sensor)


def _unwrapped_scan(scan: Scan, pixels: NDArray[np.intp], depths: NDArray[np.float32]) -> Scan:
    """The scan with its depth maps unwrapped into one range: the scene geometry, the footprint and the model all
    read depths. The maps are read as measured, the unwrapped depths of the pixels that moved (flat indices
    ``pixels`` (k,), ascending, ``depths`` (k, F) [m], kept by the validity pass) put in as they are read
    (:class:`UnwrappedDepth`); only where those would take more memory than the maps is a copy of the maps
    made, in memory (F x H x W float32, also for a scan kept in its store)."""
    unwrapped = UnwrappedDepth(scan.depth, pixels, depths)
    if pixels.nbytes + depths.nbytes > 4 * np.prod(scan.depth.shape, dtype=np.float64):
        return replace(scan, depth=unwrapped.whole(), depth_wrapped=False)
    return replace(scan, depth=cast("NDArray[np.float32]", unwrapped), depth_wrapped=False)


def _gate(flags: NDArray[np.uint8], gate: Gate, scene: SceneGeometry | None) -> tuple[str, ...]:
    """The gate's decision over the whole scan, written into the valid pixels' ``flags`` (H*W,) in place:
    UNCALIBRATED where the scan's own footprint is not significant and its bias could reach the threshold,
    NO_MULTIPATH where the gate rules multipath out. Returns what the report must say."""
    notes: tuple[str, ...] = () if scene is None else scene.notes
    if scene is not None and scene.uncalibrated is not None:
        flags[(flags == Flag.NOT_NEEDED) & scene.uncalibrated] = Flag.UNCALIBRATED
    candidates = gate.candidates(scene)
    if candidates is not None:
        flags[(flags == Flag.NOT_NEEDED) & ~candidates] = Flag.NO_MULTIPATH
    calibration = None if scene is None else scene.footprint
    if calibration is not None and calibration.pixels > 0:  # nothing to say where nothing faces
        notes += (calibration_note(calibration, int((flags == Flag.UNCALIBRATED).sum())),)
    return notes


def _predict(scan: Scan, model: CorrectionModel, sensor: SensorConfig, tiles: list[slice], gate: Gate,
             flags: NDArray[np.uint8], depth: NDArray[np.float32], inputs: PlaneModelInputs | None,
             clock: _StageClock, gate_s: float, reach: tuple[float, float] | None = None
             ) -> tuple[float, float, int]:
    """The model on the pixels the gate lets through, tile by tile (the second pass): their corrected depth into
    ``depth`` (H*W,) and CORRECTED into ``flags`` in place. Returns the gate's wall seconds (``gate_s`` plus the
    pixel-wise gate's and the geometric inputs' share), the inference's, and how many corrected pixels have
    geometric inputs beyond ``reach``, the largest rho_ABA and d_AB [m] of the model's training prior
    (:meth:`~mpi_lidar.learning.model.PriorCard.multipath_reach`; None: none counted)."""
    inference_s, beyond = 0.0, 0
    for pixels, raw in _raw_tiles(scan, tiles):
        tile_cpu, tile_started = time.process_time(), time.perf_counter()
        valid = np.flatnonzero(flags[pixels] == Flag.NOT_NEEDED)
        needs = valid[gate.needs_correction(raw[valid], scan.frequencies_hz, sensor)]
        gate_cpu, gate_wall = time.process_time() - tile_cpu, time.perf_counter() - tile_started
        if needs.size:
            depth[pixels.start + needs], inputs_cpu, inputs_wall, tile_beyond = _predict_pixels(
                model, raw[needs], pixels.start + needs, inputs, reach)
            gate_cpu, gate_wall, beyond = gate_cpu + inputs_cpu, gate_wall + inputs_wall, beyond + tile_beyond
        flags[pixels.start + needs] = Flag.CORRECTED
        # The pixel-wise gate and the geometric inputs are the gate's share of the tile; the model's inputs and
        # its prediction the rest.
        clock.add("gate", gate_cpu)
        clock.add("inference", time.process_time() - tile_cpu - gate_cpu)
        gate_s += gate_wall
        inference_s += time.perf_counter() - tile_started - gate_wall
    return gate_s, inference_s, beyond


def _beyond_prior_note(beyond: int, reach: tuple[float, float] | None) -> tuple[str, ...]:
    """What a report says of the ``beyond`` corrected pixels whose multipath lies past ``reach``, the largest
    rho_ABA and d_AB [m] of the model's training prior."""
    if not beyond or reach is None:
        return ()
    return (f"{beyond:,} corrected pixels have multipath beyond what the model was trained on (rho_ABA above "
            f"{reach[0]:g} or d_AB above {reach[1]:g} m, from the scene geometry): the model extrapolates there, "
            "and their uncertainty may be too small",)


def calibration_note(estimate: FootprintEstimate, uncalibrated: int) -> str:
    """What a report says of a scan's own footprint estimate and of the pixels it decided."""
    if not np.isfinite(estimate.area_m2):
        return (f"footprint auto: could not be measured on the {estimate.pixels:,} pixels with facing partners, "
                f"not significant: {uncalibrated:,} pixels that could hold multipath above the gate's threshold "
                "were not corrected (flag uncalibrated)")
    measured = (f"footprint auto: {estimate.area_m2:.4g} +- {estimate.sigma_m2:.2g} m^2 from {estimate.pixels:,} "
                f"pixels on {estimate.surfaces} surfaces")
    if estimate.significant:
        return f"{measured}; the coupling and the gate use it"
    return (f"{measured}, not significant: {uncalibrated:,} pixels that could hold multipath above the gate's "
            "threshold were not corrected (flag uncalibrated)")


def _predict_pixels(model: CorrectionModel, raw: NDArray, pixels: NDArray, inputs: PlaneModelInputs | None,
                    reach: tuple[float, float] | None = None) -> tuple[NDArray[np.float64], float, float, int]:
    """Corrected depth of raw rows (n, 2F) of flat pixel indices ``pixels`` (n,), the CPU seconds and the longest
    wall seconds the geometric inputs took (the gate's share), and how many rows' geometric inputs lie beyond
    ``reach`` (the largest rho_ABA and d_AB [m] of the training prior; none counted without it).

    The model's inputs, with the geometric ones of ``inputs`` where the model takes them, are built in
    row ranges on the cores into one array; the model then predicts them all at once.
    """
    features = np.empty((raw.shape[0], len(model.spec.names)), dtype=np.float32)
    top = raw.shape[1] // 2 - 1  # the highest frequency's depth column

    def build(rows: slice) -> tuple[float, float, int]:
        cpu, wall = time.thread_time(), time.perf_counter()
        geometric, beyond = None, 0
        if inputs is not None and model.geometric:
            geometric = _geometric_inputs(inputs, pixels[rows], raw[rows, top])
            if reach is not None:
                beyond = int(((geometric[:, 0] > reach[0]) | (geometric[:, 1] > reach[1])).sum())
        gate_share = (time.thread_time() - cpu, time.perf_counter() - wall)
        model.spec.transform_into(raw[rows], geometric, features[rows])
        return (*gate_share, beyond)

    shares = on_cores_by_rows(build, raw.shape[0], PARALLEL_MIN_ROWS)
    return (model.depth_from_features(raw, features), sum(cpu for cpu, _, _ in shares),
            max(wall for _, wall, _ in shares), sum(count for _, _, count in shares))


# Pixels whose geometric inputs are worked out at once: the sums over their partners' patches take about a
# kilobyte a pixel while they are made.
GEOMETRY_INPUT_PIXELS = 16_384


def _geometric_inputs(inputs: PlaneModelInputs, pixels: NDArray, measured_range: NDArray) -> NDArray[np.float64]:
    """A geometric model's inputs (n, 2) of flat pixel indices ``pixels`` (n,) whose highest-frequency range is
    ``measured_range`` (n,) [m] (:meth:`PlaneModelInputs.pixels`), ``GEOMETRY_INPUT_PIXELS`` at a time."""
    starts = range(0, max(pixels.size, 1), GEOMETRY_INPUT_PIXELS)  # no pixels: one call, for the (0, 2) shape
    return np.concatenate([geometry_inputs(*inputs.pixels(
        pixels[start:start + GEOMETRY_INPUT_PIXELS],
        measured_range[start:start + GEOMETRY_INPUT_PIXELS].astype(np.float64))) for start in starts])


def row_tiles(height: int, width: int, tile_pixels: int) -> list[slice]:
    """Flat pixel ranges of whole rows, about ``tile_pixels`` each (at least one row)."""
    rows = max(1, tile_pixels // max(width, 1))
    return [slice(top * width, min(top + rows, height) * width) for top in range(0, height, rows)]


def scan_tiles(scan: Scan, tile_pixels: int) -> list[slice]:
    """:func:`row_tiles` of a scan; for one kept in its store, those of each band of rows its maps are read in
    (:meth:`StoredMap.row_bands`), so that no tile spans two bands: a stored map keeps the last band it read,
    and a tile across two would have it read a band of twice the rows, decoding the rows it shares with the
    bands on either side once more."""
    h, w = scan.shape
    if not isinstance(scan.amplitude, StoredMap):
        return row_tiles(h, w, tile_pixels)
    return [slice(band.start * w + tile.start, band.start * w + tile.stop)
            for band in scan.amplitude.row_bands() for tile in row_tiles(band.stop - band.start, w, tile_pixels)]


def _raw_tiles(scan: Scan, tiles: list[slice]) -> Iterator[tuple[slice, NDArray[np.float32]]]:
    """(pixels, raw measurements (n, 2F) of those pixels) per tile, built from the maps' rows as needed."""
    w = scan.shape[1]
    for pixels in tiles:
        rows = slice(pixels.start // w, pixels.stop // w)
        yield pixels, replace(scan, depth=scan.depth[:, rows], amplitude=scan.amplitude[:, rows]).raw_pixels()


class _StageClock:
    """CPU seconds of this process (every thread) per named stage, summed over tiles."""

    def __init__(self) -> None:
        self.seconds: dict[str, float] = {}

    def add(self, stage: str, seconds: float) -> None:
        self.seconds[stage] = self.seconds.get(stage, 0.0) + seconds

    @contextmanager
    def __call__(self, stage: str) -> Iterator[None]:
        started = time.process_time()
        try:
            yield
        finally:
            self.add(stage, time.process_time() - started)
