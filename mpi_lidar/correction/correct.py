"""Correction of one scan, as a pipeline of named stages (:func:`correct_scan`).

Each stage is a function of its own module that returns one frozen, documented result, and reads the results of
the stages before it; none edits another's arrays. The scan's noise model (:class:`NoiseModel`, its own law where
it has the pixels to measure one) is built once and handed to every stage that weighs a measurement:

1. sensor reading (:func:`~.sensor_reading.read_sensor` -> :class:`~.sensor_reading.SensorReading`): the scan's
   own noise law, which becomes the noise model of every later stage, the amplitude unit (given, or V^2 unless the
   scan's evidence contradicts it: then the model is not applied and the scan is unserved) and saturation;
2. validity (:func:`~.validity.check_validity` -> :class:`~.validity.Validity`): unwrapping, flags, the offset
   sample and a pixel-wise gate's decision, in the first pass over the scan's tiles;
3. scene geometry (:func:`~.scene.analyse_geometry` -> :class:`~.scene.SceneGeometry`): facing surfaces, the scan's
   own footprint, the expected multipath bias, a geometric model's inputs;
4. gate (:func:`~.gating.decide` -> :class:`~.gating.GateDecision`): which valid pixels the model corrects; then
   mixed pixels (:func:`~.mixed.find_mixed` -> :class:`~.mixed.MixedPixels`): depth edges' flying pixels flagged,
   or resolved into two returns;
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
from mpi_lidar.correction.baseline import check_per_frequency, frequency_offsets
from mpi_lidar.correction.estimates import ScenePart, estimate_pixels
from mpi_lidar.correction.gates import make_gate
from mpi_lidar.correction.gating import GateDecision, decide
from mpi_lidar.correction.mixed import find_mixed
from mpi_lidar.correction.options import CorrectionOptions, Flag
from mpi_lidar.correction.prediction import in_model_range
from mpi_lidar.correction.result import Correction
from mpi_lidar.correction.scene import analyse_geometry
from mpi_lidar.correction.sensor_reading import SensorReading, read_sensor
from mpi_lidar.correction.status import unserved_reason, untrusted_unit
from mpi_lidar.correction.tiles import StageClock, in_v2, release_freed_memory, scan_tiles
from mpi_lidar.correction.validity import BeyondAmbiguity, Validity, check_validity
from mpi_lidar.errors import MpiLidarError
from mpi_lidar.learning.model import CorrectionModel
from mpi_lidar.physics.unwrap import combined_ambiguity_m
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
    check_per_frequency(options, scan.frequencies_hz, f"scan {scan.name}")
    clock = StageClock()
    tiles = scan_tiles(scan, options.tile_pixels)
    with clock("unit"):
        reading = read_sensor(scan, sensor, options)
    noise = reading.noise
    gate = make_gate(options)
    with clock("validity"):
        validity = check_validity(in_v2(scan, reading.units_per_v2), noise, options, tiles, gate,
                                  reading.saturation_v2, _beyond_ambiguity(reading, sensor))
    scan = validity.scan  # amplitudes in V^2, depths in one range: what every later stage reads
    release_freed_memory()  # the first pass's tiles' memory, before the scene geometry takes its own
    gate_started = time.perf_counter()
    with clock("gate"):
        scene = None
        if gate.uses_geometry or model.geometric:  # also for an untrusted unit: the offsets and the uncertainty
            scene = analyse_geometry(scan, validity.usable_depth, options, sensor,
                                     with_model_inputs=model.geometric and reading.unit_trusted, noise=noise,
                                     unit_trusted=reading.unit_trusted)
        decision = (decide(validity, gate, scene, model.card.dataset.prior.d_as_m, options, model.geometric)
                    if reading.unit_trusted else _model_not_applied(validity))
        mixed = find_mixed(scan, tiles, validity, decision, noise)  # flying pixels at depth edges, after the gate
        decision, validity = mixed.decision, mixed.validity
    gate_s = time.perf_counter() - gate_started
    release_freed_memory()
    part = ScenePart() if scene is None else ScenePart(
        scene.model_inputs, None if scene.bias_m is None else scene.left_alone_bias_m, scene.footprint)
    offsets = frequency_offsets(validity.offsets, decision.flags, None if scene is None else scene.blocks, options)
    pixels = estimate_pixels(scan, tiles, noise, decision.flags, validity, part, model, offsets, options, clock,
                             mixed.second_returns)
    release_freed_memory()  # before the outputs are written
    # Corrected pixels beyond the training prior keep the model's depth under their own flag.
    flags = (decision.flags if pixels.beyond_prior is None
             else np.where(pixels.beyond_prior, np.uint8(Flag.BEYOND_PRIOR), decision.flags).astype(np.uint8))
    h, w = scan.shape
    unserved = (unserved_reason(decision.flags, model.card.dataset.prior.d_as_m, options, decision.served)
                if reading.unit_trusted else untrusted_unit(reading.unit_contradiction, options))
    return Correction(
        depth=pixels.depth.reshape(h, w), flags=flags.reshape(h, w), inference_s=pixels.inference_s,
        total_s=time.perf_counter() - started, gate_s=gate_s + pixels.inputs_s,
        multipath_bias_m=None if scene is None else scene.bias_m, cpu_s=clock.seconds, calibration=part.footprint,
        unserved=unserved,
        measured_depth=validity.measured_depth.reshape(h, w),
        unwrap_confidence=None if validity.confidence is None else validity.confidence.reshape(h, w),
        estimate=pixels.estimate.reshape(h, w), uncertainty_m=pixels.uncertainty_m.reshape(h, w),
        amplitude_units_per_v2=reading.units_per_v2, reading=reading, offsets=offsets,
        scene_notes=() if scene is None else scene.notes, uncalibrated_pixels=decision.uncalibrated_pixels,
        beyond_prior_pixels=pixels.beyond_prior_pixels,
        prior_reach=model.card.dataset.prior.multipath_reach() if decision.served else None,
        second_returns=mixed.second_returns)


def _beyond_ambiguity(reading: SensorReading, sensor: SensorConfig) -> BeyondAmbiguity | None:
    """The test for ranges past the frequencies' combined ambiguity, where the frequencies have one (None
    otherwise): by amplitude and continuity where the amplitudes' unit can be trusted, by continuity alone where
    not."""
    try:
        ambiguity = combined_ambiguity_m(reading.noise.frequencies_hz, reading.noise.speed_of_light_m_per_s)
    except MpiLidarError:  # frequencies without a useful combined ambiguity: nothing to tell
        return None
    return BeyondAmbiguity(ambiguity, sensor.gamma_r_v2 if reading.unit_trusted else None)


def _model_not_applied(validity: Validity) -> GateDecision:
    """The gate's decision where the amplitudes' unit cannot be trusted: no pixel for the model (its valid pixels
    UNCALIBRATED: they get the baseline)."""
    flags = np.where(validity.flags == Flag.NOT_NEEDED, np.uint8(Flag.UNCALIBRATED), validity.flags)
    return GateDecision(flags.astype(np.uint8), int((flags == Flag.UNCALIBRATED).sum()), served=False)
