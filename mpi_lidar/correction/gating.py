"""The gate stage: which valid pixels the model corrects, from the gate's policy, the scene geometry, the
model's range and a pixel-wise gate's decision (:func:`decide`)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from mpi_lidar.correction.gates import Gate
from mpi_lidar.correction.options import CorrectionOptions, Flag
from mpi_lidar.correction.scene import SceneGeometry
from mpi_lidar.correction.validity import Validity


@dataclass(frozen=True)
class GateDecision:
    """The gate stage's result.

    flags : (H*W,) the validity flags with the gate's decisions: CORRECTED where the model is to correct,
        UNCALIBRATED where the scan's own footprint is not significant and its bias could reach the gate's
        threshold, NO_MULTIPATH where the gate rules multipath out, OUT_OF_RANGE where the model's range does not
        reach; NOT_NEEDED where a pixel-wise gate (or a model without the inputs it needs) leaves a valid pixel.
    uncalibrated_pixels : How many pixels are UNCALIBRATED.
    served : Whether the model can serve the scan at all (False: it takes geometric inputs and the scan has none).
    """

    flags: NDArray[np.uint8]
    uncalibrated_pixels: int
    served: bool


def in_depth_range(depth: NDArray, d_as_m: tuple[float, float], options: CorrectionOptions) -> NDArray[np.bool_]:
    """Whether measured depths [m] lie in the range ``d_as_m`` [m], its near end moved in by
    ``options.near_range_fraction`` of itself, both ends widened by ``options.range_tolerance_m``.

    Multipath only lengthens a path, so a depth measured near is truly near, and just below its range the model
    corrects as well as inside it; beyond its far end trees do not extrapolate, and the model pulls depths inwards.
    """
    low, high = d_as_m
    nearest = low * (1.0 - options.near_range_fraction) - options.range_tolerance_m
    return (depth >= nearest) & (depth <= high + options.range_tolerance_m)


def decide(validity: Validity, gate: Gate, scene: SceneGeometry | None, d_as_m: tuple[float, float],
           options: CorrectionOptions, geometric_model: bool) -> GateDecision:
    """The gate's decision over the whole scan (:class:`GateDecision`); ``d_as_m`` [m] is the model's range.

    The range rule comes after the gate, so that a pixel out of range that needs no correction says so
    (NO_MULTIPATH), and OUT_OF_RANGE counts only what the model failed to serve.
    """
    flags = validity.flags.copy()
    if scene is not None and scene.uncalibrated is not None:
        flags[(flags == Flag.NOT_NEEDED) & scene.uncalibrated] = Flag.UNCALIBRATED
    candidates = gate.candidates(scene)
    if candidates is not None:
        flags[(flags == Flag.NOT_NEEDED) & ~candidates] = Flag.NO_MULTIPATH
    uncalibrated = int((flags == Flag.UNCALIBRATED).sum())
    remaining = np.flatnonzero(flags == Flag.NOT_NEEDED)
    outside = ~in_depth_range(validity.usable_depth[remaining], d_as_m, options)
    flags[remaining[outside]] = Flag.OUT_OF_RANGE
    served = not (geometric_model and (scene is None or not scene.has_geometry))
    if served:
        to_correct = flags == Flag.NOT_NEEDED
        if validity.needs_correction is not None:
            to_correct &= validity.needs_correction
        flags[to_correct] = Flag.CORRECTED
    return GateDecision(flags, uncalibrated, served)
