"""``mpi-lidar calibrate``: measure a sensor's receiver footprint on its own scans and write a sensor profile."""

from __future__ import annotations

import os
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from mpi_lidar.calibration.profile import SensorProfile, write_profile
from mpi_lidar.calibration.sensor_scale import SensorScale, measure_sensor_scale
from mpi_lidar.config import SensorConfig
from mpi_lidar.constants import TABLE_SPEED_OF_LIGHT_M_PER_S
from mpi_lidar.correction.footprint import NOTHING_MEASURED, FootprintEstimate, estimate_footprint, pool_estimates
from mpi_lidar.correction.options import CorrectionOptions
from mpi_lidar.correction.scene import finer_scene_blocks, scene_blocks, settled_nowhere
from mpi_lidar.correction.sensor_reading import read_sensor
from mpi_lidar.correction.validity import depth_rules_only, usable_depth_of, validity_flags
from mpi_lidar.errors import MpiLidarError
from mpi_lidar.reporting.correction_notes import offsets_mm
from mpi_lidar.scans.scan import Scan
from mpi_lidar.scans.store import read_scan
from mpi_lidar.workflows.correct_archive import expand_archive


@dataclass(frozen=True)
class ScanEstimate:
    """One scan's footprint estimate, what its flat surfaces say of the sensor, and where it came from.

    ``depths_m`` is a sample of the scan's usable depths (at most :data:`DEPTH_SAMPLE` of them) [m].
    """

    source: str
    estimate: FootprintEstimate
    scale: SensorScale | None = None
    depths_m: NDArray[np.float64] = field(default_factory=lambda: np.zeros(0))
    # The same flat surfaces' scales with the integration window's leakage removed from the depths first: their
    # offsets tell whether the sensor has it (pool_scales).
    window_scale: SensorScale | None = None
    # The speed of light the scan's phases were converted to ranges with. [m/s]
    speed_of_light_m_per_s: float = TABLE_SPEED_OF_LIGHT_M_PER_S


# Usable depths each scan keeps for the working range's percentiles.
DEPTH_SAMPLE = 20_000


def scan_footprint(scan: Scan, options: CorrectionOptions, sensor: SensorConfig, use_reference: bool = True
                   ) -> FootprintEstimate:
    """The footprint one scan measures (:func:`scan_calibration`'s)."""
    return scan_calibration(scan, options, sensor, use_reference).estimate


def scan_calibration(scan: Scan, options: CorrectionOptions, sensor: SensorConfig, use_reference: bool = True,
                     source: str = "") -> ScanEstimate:
    """What one scan measures of its sensor: the amplitude unit, noise scale and frequency offsets on its flat
    surfaces (:func:`mpi_lidar.calibration.sensor_scale.measure_sensor_scale`, from the depths alone, so any
    amplitude unit passes), then, with its amplitudes in V^2, the footprint: against its reference depth where it
    has one (and ``use_reference``), else against its own surfaces. A scan without geometry measures nothing.

    The stages of correction (:func:`mpi_lidar.correction.correct_scan`) up to the footprint: unwrapping and
    validity over the whole scan (no model, so no model range), then the scene's blocks (:func:`scene_blocks`)."""
    if scan.ray_rows() is None:
        return ScanEstimate(source, NOTHING_MEASURED, speed_of_light_m_per_s=scan.speed_of_light_m_per_s)
    raw, confidence = scan.raw_pixels(), None
    # The scan's own noise law in its own amplitude unit: unwrapping and the consistency test need no other.
    as_read = options.model_copy(update={"amplitude_scale": 1.0})
    noise = read_sensor(scan, sensor, as_read).noise
    if scan.depth_wrapped:
        raw, confidence = noise.unwrap(raw)
        scan = replace(scan, depth=raw[:, :len(scan.frequencies_hz)].T.reshape(scan.depth.shape),
                       depth_wrapped=False)
    depth_rules = depth_rules_only(options)
    by_depth = usable_depth_of(raw, validity_flags(raw, depth_rules, noise, confidence))
    scale = measure_sensor_scale(scan, by_depth, options, sensor)
    if not scale.significant and scale.pixels > 0:  # one noise regime: the unit, with the noise model's noise
        with_model_noise = measure_sensor_scale(scan, by_depth, options, sensor, fix_noise_scale=1.0)
        scale = with_model_noise if with_model_noise.significant else scale
    window_scale = None
    if scale.significant:
        raw = raw.copy()
        raw[:, len(scan.frequencies_hz):] /= scale.amplitude_scale
        scan = replace(scan, amplitude=(np.asarray(scan.amplitude) / scale.amplitude_scale).astype(np.float32))
        window_scale = measure_sensor_scale(scan, by_depth, options, sensor, window=True,
                                            fix_noise_scale=None if scale.noise_scale_sigma > 0 else scale.noise_scale)
        noise = read_sensor(scan, sensor, as_read).noise  # the same law, in V^2
    usable_depth = usable_depth_of(raw, validity_flags(raw, options, noise, confidence))
    valid = np.isfinite(usable_depth)
    blocks = scene_blocks(scan, usable_depth, options)
    assert blocks is not None  # the scan has rays
    reference = use_reference and scan.reference_depth is not None
    if reference:
        valid &= np.isfinite(np.asarray(scan.reference_depth, dtype=np.float64)).ravel()
    depths = usable_depth[np.isfinite(usable_depth)].astype(np.float64)
    sample = depths[np.linspace(0, depths.size - 1, min(DEPTH_SAMPLE, depths.size)).astype(np.intp)]
    estimate = estimate_footprint(scan, blocks, valid, sensor, reference=reference)
    finer = finer_scene_blocks(scan, usable_depth, options, None, blocks) if settled_nowhere(estimate) else None
    if finer is not None:  # a coarse scan measured again on finer blocks, as correction does
        on_finer = estimate_footprint(scan, finer, valid, sensor, reference=reference)
        estimate = on_finer if on_finer.significant else estimate  # calibration pools significant ones alone
    return ScanEstimate(source, estimate, scale, sample, window_scale, scan.speed_of_light_m_per_s)


def calibrate_scans(inputs: list[str], out: str | Path, options: CorrectionOptions | None = None,
                    use_reference: bool = True, on_scan: Callable[[ScanEstimate], None] | None = None
                    ) -> tuple[SensorProfile, list[ScanEstimate]]:
    """Pool what every scan of ``inputs`` (stores, directories, globs) measures and write the profile to ``out``.

    The footprint is pooled by its uncertainty; a pooled footprint that is not significant writes nothing (the
    scans hold too little facing geometry). The amplitude unit, noise scale and frequency offsets are pooled
    over the scans whose flat surfaces measured them (:func:`pool_scales`); the working range is the 1st to
    99th percentile of the scans' usable depths; the frequencies and the speed of light are the scans' (all must
    share them). Scans whose amplitude units differ more than twofold beyond their uncertainties
    (:func:`check_units_agree`) write nothing: they are not one sensor's, or not in one unit.
    """
    options = options or CorrectionOptions()
    if Path(out).exists():
        raise MpiLidarError(f"sensor profile {out} already exists; choose another --out or remove it")
    sources = expand_archive(inputs)
    results: list[ScanEstimate] = []
    frequencies: set[tuple[float, ...]] = set()
    for source in sources:
        scan = read_scan(source)
        frequencies.add(scan.frequencies_hz)
        if len(frequencies) > 1:
            raise MpiLidarError(f"scan {source} was measured at other frequencies than the scans before it; "
                                "calibrate one sensor's scans at a time")
        if results and scan.speed_of_light_m_per_s != results[0].speed_of_light_m_per_s:
            raise MpiLidarError(f"scan {source} converts phase to range with c = {scan.speed_of_light_m_per_s:.9g} "
                                f"m/s, scan {results[0].source} with {results[0].speed_of_light_m_per_s:.9g} m/s; "
                                "calibrate one sensor's scans at a time (import them with the --speed-of-light its "
                                "firmware uses)")
        # The scan's phases unwrap with the periods c / 2f of the c its depths were converted with.
        sensor = SensorConfig(speed_of_light_m_per_s=scan.speed_of_light_m_per_s)
        result = scan_calibration(scan, options, sensor, use_reference, source)
        results.append(result)
        if on_scan:
            on_scan(result)
    check_units_agree(results)
    pooled = pool_estimates([r.estimate for r in results])
    if not pooled.significant:
        raise MpiLidarError(
            f"{'the scan gives' if len(sources) == 1 else f'the {len(sources)} scans give'} no significant footprint "
            f"({_describe(pooled)}); calibrate on scans "
            "with corners or other surfaces facing each other, or give --footprint-area-m2 to correct")
    measured: dict[str, object] = {"saturation_amplitude_v2": options.saturation_amplitude_v2,
                                   "min_amplitude_sigmas": options.min_amplitude_sigmas,
                                   "frequencies_hz": next(iter(frequencies)) if frequencies else None,
                                   "speed_of_light_m_per_s": results[0].speed_of_light_m_per_s if results else None}
    measured.update(pool_scales([r.scale for r in results if r.scale is not None],
                                [r.window_scale for r in results if r.window_scale is not None]))
    depths = np.concatenate([r.depths_m for r in results]) if results else np.zeros(0)
    near, far = (float(np.quantile(depths, 0.01)), float(np.quantile(depths, 0.99))) if depths.size else (0, 0)
    if 0 < near < far:  # a working range only where the depths span one
        measured["range_m"] = (near, far)
    profile = SensorProfile.from_estimate(pooled, [printable_path(source) for source in sources],
                                          [printable_path(describe_scan(r)) for r in results], **measured)
    write_profile(profile, out)
    return profile, results


# How many times one scan's amplitude unit may be another's, beyond their uncertainties, for one sensor's scans.
MAX_UNIT_RATIO = 2.0


def check_units_agree(results: list[ScanEstimate]) -> None:
    """Refuse scans whose measured amplitude units differ more than :data:`MAX_UNIT_RATIO`-fold beyond twice their
    combined uncertainty (in log), with one line naming the two scans farthest apart."""
    measured = [r for r in results if r.scale is not None and r.scale.significant]
    if len(measured) < 2:
        return
    logs = np.array([np.log(r.scale.amplitude_scale) for r in measured if r.scale is not None])
    sigmas = np.array([r.scale.amplitude_scale_sigma / r.scale.amplitude_scale for r in measured
                       if r.scale is not None])
    low, high = int(np.argmin(logs)), int(np.argmax(logs))
    if logs[high] - logs[low] - 2 * np.hypot(sigmas[low], sigmas[high]) <= np.log(MAX_UNIT_RATIO):
        return
    a, b = measured[low], measured[high]
    assert a.scale is not None and b.scale is not None
    raise MpiLidarError(f"scan {a.source} reads {_unit(a.scale)} per V^2, scan {b.source} {_unit(b.scale)} per "
                        f"V^2: their amplitudes are in units {b.scale.amplitude_scale / a.scale.amplitude_scale:.3g}"
                        "-fold apart; calibrate one sensor's scans in one amplitude unit at a time")


def _unit(scale: SensorScale) -> str:
    return f"{scale.amplitude_scale:.4g} +- {scale.amplitude_scale_sigma:.2g}"


def describe_scan(result: ScanEstimate) -> str:
    """One line of what one scan measured (footprint, amplitude unit and noise, frequency offsets, speed of light)."""
    scale = result.scale
    offsets = ""
    if scale is not None and scale.significant and np.isfinite(scale.offsets_m).all():
        offsets = f"; frequency offsets {offsets_mm(tuple(float(o) for o in scale.offsets_m))} mm"
    return (f"{result.source}: {describe(result.estimate)}; {describe_scale(scale)}{offsets}; "
            f"c = {result.speed_of_light_m_per_s:.9g} m/s")


def printable_path(path: str | Path) -> str:
    """A path as text that any UTF-8 file holds: a byte of a file name that is not UTF-8 (which Python keeps as a
    lone surrogate, ``\\udcff``) becomes ``\\xff``. The profile's ``calibration.sources`` record where its
    scans were, for people; TOML cannot hold a lone surrogate, and the profile must read back."""
    return os.fsencode(path).decode("utf-8", "backslashreplace")


def pool_scales(scales: list[SensorScale], window_scales: list[SensorScale] | None = None) -> dict[str, object]:
    """The profile's amplitude_scale, noise_scale and frequency_offsets_m from the significant scans' estimates,
    each weighted by its inverse variance (the scales in log); empty where no scan measured them.

    ``window_scales``: the same scans' estimates with the integration window's leakage removed from the depths. The
    profile says whether its sensor has the leakage (``window_leakage_removed``): it does where the pooled offsets
    are smaller (in sum of squares) with the leakage removed, and its offsets are then those.
    """
    good = [s for s in scales if s.significant]
    if not good:
        return {}
    log_scale = np.array([np.log(s.amplitude_scale) for s in good])
    scale_weight = np.array([(s.amplitude_scale / s.amplitude_scale_sigma) ** 2 for s in good])
    pooled: dict[str, object] = {"amplitude_scale": float(np.exp(np.average(log_scale, weights=scale_weight)))}
    fitted = [s for s in good if 0 < s.noise_scale_sigma < np.inf]
    if fitted:
        noise_weight = np.array([(s.noise_scale / s.noise_scale_sigma) ** 2 for s in fitted])
        pooled["noise_scale"] = float(np.exp(np.average([np.log(s.noise_scale) for s in fitted],
                                                        weights=noise_weight)))
    offsets = _pooled_offsets(good)
    windowed = [s for s in window_scales or [] if np.isfinite(s.offsets_m).all()]
    if len(windowed) == len(good):
        with_window = _pooled_offsets(windowed)
        pooled["window_leakage_removed"] = bool(np.sum(with_window**2) < np.sum(offsets**2))
        offsets = with_window if pooled["window_leakage_removed"] else offsets
    pooled["frequency_offsets_m"] = tuple(float(o) for o in offsets)
    return pooled


def _pooled_offsets(scales: list[SensorScale]) -> NDArray[np.float64]:
    """The frequencies' offsets (F,) [m] of the scans' estimates, each weighted by its inverse variance."""
    offsets = np.array([s.offsets_m for s in scales])
    weights = 1.0 / np.maximum(np.array([s.offsets_sigma_m for s in scales]), 1e-9) ** 2
    return (offsets * weights).sum(0) / weights.sum(0)


def _describe(estimate: FootprintEstimate) -> str:
    if not np.isfinite(estimate.area_m2):
        return "no facing surfaces found"
    return f"{estimate.area_m2:.4g} +- {estimate.sigma_m2:.2g} m^2 from {estimate.pixels:,} pixels"


def describe(estimate: FootprintEstimate) -> str:
    """One line of a scan's or a pool's estimate, for the command line."""
    verdict = "significant" if estimate.significant else "not significant"
    return f"{_describe(estimate)} ({estimate.method}, {verdict})"


def describe_scale(scale: SensorScale | None) -> str:
    """One line of what a scan's flat surfaces say of its amplitude unit and noise, for the command line."""
    if scale is None or not scale.significant:
        why = "no geometry" if scale is None else scale.reason
        return f"amplitude unit not measured ({why})"
    noise = (f"noise scale {scale.noise_scale:.3g} +- {scale.noise_scale_sigma:.2g}"
             if 0 < scale.noise_scale_sigma < np.inf else "noise scale not separable")
    return (f"amplitude unit {scale.amplitude_scale:.4g} +- {scale.amplitude_scale_sigma:.2g} per V^2, {noise} "
            f"({scale.pixels:,} flat pixels)")
