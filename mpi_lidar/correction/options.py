"""What correction may do and how a pixel or a scan ended: flags, statuses, validated options."""

from __future__ import annotations

import hashlib
import json
from enum import IntEnum, StrEnum
from typing import Annotated, Final, Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, ValidationError

from mpi_lidar.config import describe_validation_error
from mpi_lidar.correction.gate_names import GATES as GATES  # re-exported: the gates of the options
from mpi_lidar.correction.gate_names import GateName
from mpi_lidar.errors import MpiLidarError
from mpi_lidar.physics.unwrap import MIN_UNWRAP_CONFIDENCE
from mpi_lidar.scans import geometry

CORRECTED_SCHEMA = "mpi-lidar/corrected@1"
AUTO: Final = "auto"  # footprint_area_m2: each scan measures its own (mpi_lidar.correction.footprint)



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
    UNCALIBRATED = 8
    AMBIGUOUS = 9


INVALID_FLAGS = (Flag.NOT_FINITE, Flag.NO_RETURN, Flag.SATURATED, Flag.INCONSISTENT)

class ScanStatus(StrEnum):
    """How one scan of a batch ended (:func:`mpi_lidar.correction.outcome.scan_status` decides the first three).

    corrected: pixels were corrected. unchanged: valid outputs, but no pixel was corrected (a flat wall under
    the geometry gate, every pixel gated out, or a scan without geometry under a geometric model). degraded:
    the share of invalid pixels (not finite, no return, saturated, inconsistent) is above
    ``CorrectionOptions.max_invalid_share``, whether or not pixels were corrected (a sensor with another gain,
    a fogged window). unserved: the model cannot serve the scan (:class:`UnservedReason`): its outputs hold
    the pixels as measured, and the batch fails unless told otherwise. skipped: already corrected with the
    same model and options. failed: no outputs.
    """

    CORRECTED = "corrected"
    UNCHANGED = "unchanged"
    DEGRADED = "degraded"
    UNSERVED = "unserved"
    SKIPPED = "skipped"
    FAILED = "failed"


class UnservedReason(StrEnum):
    """Why a model cannot serve a scan (status unserved), as recorded in ``metrics.json`` and the summary.

    out_of_range: every pixel that may need correction lies outside the range the model was trained for;
    no_geometry: the model takes geometric inputs and the scan has no geometry; amplitude_units: more than
    90 % of the measured pixels read as saturated, as amplitudes in another unit than the model's do;
    ambiguous_range: more than half of the measured pixels have an ambiguous range (the frequencies' wrap
    counts could not be told apart).
    """

    OUT_OF_RANGE = "out_of_range"
    NO_GEOMETRY = "no_geometry"
    AMPLITUDE_UNITS = "amplitude_units"
    AMBIGUOUS_RANGE = "ambiguous_range"


STATUS_ONLY_OPTIONS = frozenset({"max_invalid_share"})  # options that never change a pixel: not hashed

Positive = Annotated[float, Field(gt=0)]
NonNegative = Annotated[float, Field(ge=0)]


class CorrectionOptions(BaseModel):
    """Thresholds of the validity mask and the gate, bounds checked.

    Their hash is part of a corrected scan's identity.
    """

    model_config = ConfigDict(frozen=True, extra="forbid", allow_inf_nan=False)

    gate: GateName = GateName.GEOMETRY
    min_amplitude_sigmas: NonNegative = 5.0
    saturation_amplitude_v2: Positive = 0.7176  # a perfect reflector at 0.5 m; set it from your sensor
    max_depth_spread_m: Positive = 0.3
    # Zero: near the far end of its prior the model pulls depths inwards, so beyond it raw depth is safer.
    range_tolerance_m: NonNegative = 0.0
    # Multipath only lengthens a path, so a depth measured nearer than the prior's nearest d_AS is truly that
    # near, and down to 15 % nearer the model's error is that of the prior's own near end
    # (benchmarks/model_range.py): such depths are corrected, not left raw.
    near_range_fraction: Annotated[float, Field(ge=0, lt=1)] = 0.15
    consistency_p_value: Annotated[float, Field(gt=0, lt=1)] = 0.01
    # A wrapped scan's pixels whose wrap counts have a lower posterior probability than this are ambiguous:
    # left as measured (flag ambiguous). At 0.999 fewer than 0.1 % of the pixels kept are expected to be
    # unwrapped wrong where the noise model holds (mpi_lidar.physics.unwrap).
    min_unwrap_confidence: Annotated[float, Field(gt=0, lt=1)] = MIN_UNWRAP_CONFIDENCE
    min_multipath_bias_m: NonNegative = 0.004
    geometry_block_m: Positive = geometry.DEFAULT_BLOCK_M
    partner_range_m: Positive = geometry.DEFAULT_MAX_RANGE_M
    # The receiver footprint A_fp [m^2] that scales the geometric coupling, or "auto": each scan estimates its
    # own from the depth and amplitude near its facing surfaces (mpi_lidar.correction.footprint).
    footprint_area_m2: Positive | Literal["auto"] = AUTO
    # The scanner's amplitude unit per V^2, the noise model's unit: a scan's amplitudes are divided by it before
    # anything reads them (thresholds, albedo, the model's inputs). 1: amplitudes in V^2. "auto": each scan
    # measures its own on its flat surfaces (mpi_lidar.correction.sensor_scale); where that is not significant
    # the scan's pixels are left as measured and it ends unserved (amplitude_units).
    amplitude_scale: Positive | Literal["auto"] = 1.0
    tile_pixels: Annotated[int, Field(ge=1)] = 262_144
    # Above this share of invalid pixels a scan is 'degraded', not 'corrected': past half the map the
    # outputs describe the sensor setup (gain, saturation level, range) more than the scene, and a batch
    # should say so rather than report success. It only names how a scan ended, never changes a pixel.
    max_invalid_share: Annotated[float, Field(ge=0, le=1)] = 0.5
    # The sensor profile (sensor.toml) the footprint and thresholds came from: the hash of its values.
    sensor_profile_sha256: str | None = None

    def sha256(self) -> str:
        """Identity of what the options do to the pixels: part of a corrected scan's identity.

        Fields that only classify the outcome (``max_invalid_share``) are left out, always: changing them
        must not re-correct a scan, and outputs written before they existed keep their hash.
        """
        pixels = self.model_dump(exclude=set(STATUS_ONLY_OPTIONS))
        if pixels["sensor_profile_sha256"] is None:  # hashes from before profiles existed stay the same
            del pixels["sensor_profile_sha256"]
        if pixels["near_range_fraction"] == 0:  # the rule before it existed: those outputs keep their hash
            del pixels["near_range_fraction"]
        if pixels["amplitude_scale"] == 1.0:  # V^2, as before the scale existed
            del pixels["amplitude_scale"]
        return hashlib.sha256(json.dumps(pixels, sort_keys=True).encode()).hexdigest()

    @property
    def self_calibrating(self) -> bool:
        """Whether each scan estimates its own footprint (``footprint_area_m2`` = "auto")."""
        return self.footprint_area_m2 == AUTO

    @classmethod
    def from_cli(cls, gate: str = "geometry", min_bias_mm: float | None = None,
                 footprint_area_m2: float | str | None = None, max_invalid_share: float | None = None,
                 sensor_profile: dict[str, float | str] | None = None,
                 amplitude_scale: float | str | None = None) -> CorrectionOptions:
        """The options of ``mpi-lidar correct`` and of the correction flow, in their units; None keeps a default.

        ``min_bias_mm`` is the geometry gate's threshold in millimetres (``min_multipath_bias_m`` x 1000);
        ``footprint_area_m2`` a number or "auto"; ``sensor_profile`` the options a sensor profile sets
        (:meth:`mpi_lidar.correction.profile.SensorProfile.options`), which the other arguments override.
        Out-of-range values are refused with one line.
        """
        overrides = {**(sensor_profile or {}),
                     **{k: v for k, v in {"min_multipath_bias_m": None if min_bias_mm is None else min_bias_mm / 1e3,
                                          "footprint_area_m2": _positive_or_auto("footprint_area_m2",
                                                                                 footprint_area_m2,
                                                                                 "square metres (e.g. 0.02)"),
                                          "max_invalid_share": max_invalid_share,
                                          "amplitude_scale": _positive_or_auto("amplitude_scale", amplitude_scale,
                                                                               "units per V^2 (e.g. 4000)"),
                                          }.items() if v is not None}}
        try:
            return cls(gate=gate, **overrides)
        except ValidationError as exc:
            problems = describe_validation_error(exc, "options", shown=None, verbatim=True)
            raise MpiLidarError(f"invalid correction options ({problems})") from None


def _positive_or_auto(name: str, value: float | str | None, unit: str) -> float | str | None:
    """An option given on a command line or in a flow parameter: "auto", a positive number, or None."""
    if value is None:
        return None
    if isinstance(value, str) and value.strip().lower() == AUTO:
        return AUTO
    try:
        number = float(value)
    except (TypeError, ValueError):
        number = float("nan")
    if not np.isfinite(number) or number <= 0:
        raise MpiLidarError(f"{name} must be 'auto' or a positive number of {unit}, got {value!r}")
    return number
