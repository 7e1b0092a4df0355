"""Correction of one scan, as a pipeline of named stages (:func:`correct_scan`).

Each stage is a function of its own module that returns one frozen, documented result, and reads the results of
the stages before it; none edits another's arrays. The scan's noise model (:class:`NoiseModel`) is built once and
handed to every stage that weighs a measurement:

1. amplitude unit (:func:`~.amplitude_unit.read_amplitude_unit` -> :class:`~.amplitude_unit.UnitReading`): the
   scanner's unit per V^2; a scan whose unit cannot be known is left as measured (status unserved);
2. validity (:func:`~.validity.check_validity` -> :class:`~.validity.Validity`): unwrapping, flags, the offset
   sample and a pixel-wise gate's decision, in the first pass over the scan's tiles;
3. scene geometry (:func:`~.scene.analyse_geometry` -> :class:`~.scene.SceneGeometry`): facing surfaces, the scan's
   own footprint, the expected multipath bias, a geometric model's inputs;
4. gate (:func:`~.gating.decide` -> :class:`~.gating.GateDecision`): which valid pixels the model corrects;
5. baseline offsets (:func:`~.baseline.frequency_offsets` -> :class:`~.baseline.FrequencyOffsets`);
6. per-pixel estimate (:func:`~.estimates.estimate_pixels` -> :class:`~.estimates.PixelEstimates`): the model's
   depth, the fused baseline's and every pixel's uncertainty, in the second and last pass over the tiles;
7. status (:func:`~.status.unserved_reason`).

A new stage follows the same contract: a function of the earlier stages' results (and the noise model and options)
that returns a frozen dataclass documenting each field with its unit, and adds what the outputs need to
:class:`~.result.Correction`.
"""

from __future__ import annotations

import time

import numpy as np

from mpi_lidar.config import SensorConfig
from mpi_lidar.correction.amplitude_unit import UnitReading, read_amplitude_unit
from mpi_lidar.correction.baseline import frequency_offsets
from mpi_lidar.correction.estimates import ScenePart, estimate_pixels
from mpi_lidar.correction.gates import make_gate
from mpi_lidar.correction.gating import decide
from mpi_lidar.correction.options import INVALID_FLAGS, CorrectionOptions, Estimate, Flag
from mpi_lidar.correction.prediction import in_model_range
from mpi_lidar.correction.result import Correction
from mpi_lidar.correction.scene import analyse_geometry
from mpi_lidar.correction.status import unknown_unit, unserved_reason
from mpi_lidar.correction.tiles import StageClock, in_v2, scan_tiles
from mpi_lidar.correction.validity import Validity, check_validity, depth_rules_only
from mpi_lidar.learning.model import CorrectionModel
from mpi_lidar.physics.noise import NoiseModel
from mpi_lidar.scans.scan import Scan

__all__ = ["Correction", "correct_scan", "in_model_range"]


def correct_scan(scan: Scan, model: CorrectionModel, options: CorrectionOptions | None = None,
                 sensor: SensorConfig | None = None) -> Correction:
    """Correct one scan in this process, stage by stage (the module's docstring), in tiles of whole rows of about
    ``options.tile_pixels`` pixels.

    Parameters
    ----------
    scan : The scan; its maps may stay in the store (:class:`mpi_lidar.scans.stored_map.StoredMap`).
    model : The correction model; the scan's frequencies must be the model's.
    options : What correction may do (None: the defaults).
    sensor : The sensor whose noise model weighs the measurements (None: the default sensor).

    Returns
    -------
    Correction
        Every pixel's depth, flag, estimate and uncertainty, and what each stage found. Every pixel gets exactly
        the value it gets from the whole scan in memory at once, tiled or not.
    """
    started = time.perf_counter()
    options = options or CorrectionOptions()
    sensor = sensor or SensorConfig()
    model.check_compatible(scan.frequencies_hz, model.spec.raw_names, f"scan {scan.name}")
    clock = StageClock()
    tiles = scan_tiles(scan, options.tile_pixels)
    noise = NoiseModel.for_sensor(sensor, scan.frequencies_hz, options.noise_scale)
    with clock("unit"):
        unit = read_amplitude_unit(scan, noise, options)
    if not unit.known:
        return _left_as_measured(scan, check_validity(scan, noise, depth_rules_only(options), tiles), unit, started)
    gate = make_gate(options)
    with clock("validity"):
        validity = check_validity(in_v2(scan, unit.units_per_v2), noise, options, tiles, gate)
    scan = validity.scan  # amplitudes in V^2, depths in one range: what every later stage reads
    gate_started = time.perf_counter()
    with clock("gate"):
        scene = None
        if gate.uses_geometry or model.geometric:
            scene = analyse_geometry(scan, validity.usable_depth, options, sensor,
                                     with_model_inputs=model.geometric, noise=noise)
        decision = decide(validity, gate, scene, model.card.dataset.prior.d_as_m, options, model.geometric)
    gate_s = time.perf_counter() - gate_started
    part = ScenePart() if scene is None else ScenePart(scene.model_inputs, scene.bias_m, scene.footprint)
    offsets = frequency_offsets(validity.offsets, decision.flags, part.bias_m, options)
    pixels = estimate_pixels(scan, tiles, noise, decision.flags, validity, part, model, offsets, options, clock)
    h, w = scan.shape
    return Correction(
        depth=pixels.depth.reshape(h, w), flags=decision.flags.reshape(h, w), inference_s=pixels.inference_s,
        total_s=time.perf_counter() - started, gate_s=gate_s + pixels.inputs_s, multipath_bias_m=part.bias_m,
        cpu_s=clock.seconds, calibration=part.footprint,
        unserved=unserved_reason(decision.flags, model.card.dataset.prior.d_as_m, options, decision.served),
        measured_depth=validity.measured_depth.reshape(h, w),
        unwrap_confidence=None if validity.confidence is None else validity.confidence.reshape(h, w),
        estimate=pixels.estimate.reshape(h, w), uncertainty_m=pixels.uncertainty_m.reshape(h, w),
        amplitude_units_per_v2=unit.units_per_v2, amplitude_unit=unit.measured, offsets=offsets,
        scene_notes=() if scene is None else scene.notes, uncalibrated_pixels=decision.uncalibrated_pixels,
        beyond_prior_pixels=pixels.beyond_prior_pixels,
        prior_reach=model.card.dataset.prior.multipath_reach() if decision.served else None)


def _left_as_measured(scan: Scan, validity: Validity, unit: UnitReading, started: float) -> Correction:
    """A scan whose amplitude unit could not be measured: validity from the depths alone, every valid pixel as
    measured (flag uncalibrated), the scan unserved for its amplitude unit, no uncertainty (the noise model needs
    the amplitudes' unit)."""
    flags = np.where(validity.flags == Flag.NOT_NEEDED, np.uint8(Flag.UNCALIBRATED), validity.flags)
    depth = np.where(flags == Flag.AMBIGUOUS, validity.measured_depth, validity.usable_depth).astype(np.float32)
    h, w = scan.shape
    assert unit.measured is not None  # only a reading can be unknown
    return Correction(
        depth=depth.reshape(h, w), flags=flags.reshape(h, w), total_s=time.perf_counter() - started,
        unserved=unknown_unit(unit.measured.reason), measured_depth=validity.measured_depth.reshape(h, w),
        unwrap_confidence=None if validity.confidence is None else validity.confidence.reshape(h, w),
        estimate=np.where(np.isin(flags, [int(flag) for flag in INVALID_FLAGS]), Estimate.NONE,
                          Estimate.MEASURED).astype(np.uint8).reshape(h, w),
        uncertainty_m=np.full((h, w), np.nan, dtype=np.float32),
        amplitude_units_per_v2=1.0, amplitude_unit=unit.measured)
