"""What correction may do and how a pixel or a scan ended: flags, statuses, validated options."""

from __future__ import annotations

import hashlib
import json
from dataclasses import dataclass
from enum import IntEnum, StrEnum
from typing import Annotated, Final, Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, StrictBool, ValidationError

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
    # Past the frequencies' combined ambiguity: its amplitude is far too weak for the range its phases give.
    BEYOND_AMBIGUITY = 10
    # A depth edge in the footprint: the frequencies disagree beyond their noise beside a neighbour far nearer or
    # farther, so the one depth they give is no surface's (mpi_lidar.correction.mixed).
    MIXED = 11
    # The same, resolved into two returns: the depth is the stronger return's, the weaker is kept beside it.
    TWO_RETURNS = 12
    # Corrected by the model, but its geometric inputs lie beyond the training prior's reach: the model's depth, with
    # an uncertainty widened by the share of the multipath the prior leaves out (mpi_lidar.learning.error_model).
    BEYOND_PRIOR = 13


class Estimate(IntEnum):
    """Which estimate a pixel's output depth is (``estimate`` in ``corrected.zarr``).

    none: no depth (NaN, an invalid pixel). measured: the highest frequency's depth as measured (unwrapped where
    the scan's depths wrapped): under ``--baseline raw``, and where the frequencies disagree beyond their noise, the
    range is ambiguous or the amplitudes' unit is not known. fused: the frequencies' depths fused by inverse
    variance, for a valid pixel the model does not correct. corrected: the model's.
    """

    NONE = 0
    MEASURED = 1
    FUSED = 2
    CORRECTED = 3


class Baseline(StrEnum):
    """What a valid pixel that the model does not correct gets: ``fused`` (default), the frequencies' depths fused by
    inverse variance where they agree within noise; ``raw``, the highest frequency's depth as measured."""

    FUSED = "fused"
    RAW = "raw"


# The pixels whose depth is the model's: corrected inside the training prior and beyond it.
MODEL_FLAGS = (Flag.CORRECTED, Flag.BEYOND_PRIOR)
INVALID_FLAGS = (Flag.NOT_FINITE, Flag.NO_RETURN, Flag.SATURATED, Flag.INCONSISTENT, Flag.BEYOND_AMBIGUITY,
                 Flag.MIXED)

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


# The statuses --fail-on / fail_on may name; failed always fails a batch, unserved unless allowed.
FAIL_ON = (ScanStatus.DEGRADED, ScanStatus.UNCHANGED, ScanStatus.FAILED)


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

# Physical bounds (docs/reference/configuration.md, "Physical bounds"): a value past them is a unit mistake or a
# typo, refused before a pixel is touched. Numbers are strict: a boolean or a string is no number of metres.
MAX_FOOTPRINT_AREA_M2 = 1.0  # no receiver footprint reaches a square metre (as the footprint fit's own bound)
MAX_AMPLITUDE_V2 = 1e4  # a detector chain's amplitude [V^2]: volts squared, never ten thousand
NO_SATURATION_V2 = 1e30  # the one larger saturation threshold: none (validity from the depths alone)
AMPLITUDE_SCALE_BOUNDS = (1e-6, 1e9)  # a scanner's amplitude unit per V^2 that keeps float32 amplitudes finite
MAX_SIGMAS = 100.0  # noise deviations
# A sensor's depth noise over the noise model's [1]: a thousandth is a sensor far quieter than photons allow;
# below it every depth's uncertainty would round to nothing.
NOISE_SCALE_BOUNDS = (1e-3, 100.0)
MAX_DEPTH_M = 1000.0  # depths, spreads and tolerances: beyond any AMCW LiDAR's range
MAX_BIAS_M = 1.0  # a multipath bias: millimetres to centimetres; a metre is no threshold of one
MAX_BLOCK_M = 10.0  # a geometry block's side
MAX_TILE_PIXELS = 1 << 30

Positive = Annotated[float, Field(gt=0, strict=True)]
NonNegative = Annotated[float, Field(ge=0, strict=True)]
Fraction = Annotated[float, Field(gt=0, lt=1, strict=True)]


class CorrectionOptions(BaseModel):
    """Thresholds of the validity mask and the gate, bounds checked.

    Their hash is part of a corrected scan's identity. The fields a user sets carry their help text as their
    description; :data:`USER_OPTIONS` names the option of ``mpi-lidar correct`` and the parameter of the
    correction flow that set each.
    """

    model_config = ConfigDict(frozen=True, extra="forbid", allow_inf_nan=False)

    gate: GateName = Field(GateName.GEOMETRY, description=(
        "Which valid pixels get corrected: where the scan's geometry allows multipath (geometry; on scans without "
        "geometry a pixel-wise model corrects every valid pixel and a geometric model, the default, leaves them as "
        "measured: status unchanged), every valid pixel (all), or frequency disagreement (consistency)."))
    # No return: the frequencies' light together below what no light reaches as rarely as one frequency reaches this
    # many times the no-light noise of the scan's own noise law (its read term); where a surface past the combined
    # ambiguity could give the amplitude, any one frequency below it; or none at all.
    min_amplitude_sigmas: Annotated[float, Field(ge=0, le=MAX_SIGMAS, strict=True)] = 5.0
    # The amplitude above which a pixel is saturated [V^2], from a sensor profile or the user. None: from the scan
    # itself (a plateau of clipped amplitudes), never from a sensor table's limit in a guessed unit.
    saturation_amplitude_v2: Annotated[float, Field(gt=0, le=NO_SATURATION_V2, strict=True)] | None = None
    # (A sensor profile, the options' source, holds at most MAX_AMPLITUDE_V2.)
    # Deprecated: a fixed spread of the frequencies' depths [m] past which a pixel is inconsistent. Consistency is
    # judged in units of the noise (inconsistent_p_value); a value given here applies as well.
    max_depth_spread_m: Annotated[float, Field(gt=0, le=MAX_DEPTH_M, strict=True)] | None = None
    # A pixel whose frequencies disagree beyond chi-square's (1 - this) quantile under the scan's own noise law
    # cannot be one range: inconsistent (invalid). Far beyond what multipath does to them (almost the same offset
    # at every frequency); a wrong wrap count, a depth edge or a broken frequency.
    inconsistent_p_value: Annotated[float, Field(gt=0, lt=0.01, strict=True)] = 1e-6
    # Zero: near the far end of its prior the model pulls depths inwards, so beyond it raw depth is safer.
    range_tolerance_m: Annotated[float, Field(ge=0, le=MAX_DEPTH_M, strict=True)] = 0.0
    # Multipath only lengthens a path, so a depth measured nearer than the prior's nearest d_AS is truly that
    # near, and down to 15 % nearer the model's error is that of the prior's own near end
    # (benchmarks/model_range.py): such depths are corrected, not left raw.
    near_range_fraction: Annotated[float, Field(ge=0, lt=1, strict=True)] = 0.15
    consistency_p_value: Fraction = 0.01
    # A wrapped scan's pixels whose wrap counts have a lower posterior probability than this are ambiguous:
    # left as measured (flag ambiguous). At 0.999 fewer than 0.1 % of the pixels kept are expected to be
    # unwrapped wrong where the noise model holds (mpi_lidar.physics.unwrap).
    min_unwrap_confidence: Fraction = MIN_UNWRAP_CONFIDENCE
    min_multipath_bias_m: Annotated[float, Field(ge=0, le=MAX_BIAS_M, strict=True)] = Field(0.002, description=(
        "Geometry gate: correct pixels whose expected multipath bias reaches this (a geometric model corrects a "
        "bias of 2 mm to below it on the rendered corners and rooms, see docs/results/scenes.md)."))
    geometry_block_m: Annotated[float, Field(gt=0, le=MAX_BLOCK_M, strict=True)] = geometry.DEFAULT_BLOCK_M
    partner_range_m: Annotated[float, Field(gt=0, le=MAX_DEPTH_M, strict=True)] = geometry.DEFAULT_MAX_RANGE_M
    # auto: mpi_lidar.correction.footprint, from the depth and amplitude near the scan's facing surfaces.
    footprint_area_m2: Annotated[float, Field(gt=0, le=MAX_FOOTPRINT_AREA_M2, strict=True)] | Literal["auto"] = Field(
        AUTO, description=(
            "Effective receiver footprint of your sensor, which scales the geometric coupling, or auto: each scan "
            "measures its own from its facing surfaces, and pixels that depend on an estimate that is not "
            "significant are not corrected (flag uncalibrated)."))
    # The model's inputs, the albedo and the radiometric limits read amplitudes in V^2.
    # auto: mpi_lidar.correction.sensor_reading.
    amplitude_scale: (Annotated[float, Field(ge=AMPLITUDE_SCALE_BOUNDS[0], le=AMPLITUDE_SCALE_BOUNDS[1], strict=True)]
                      | Literal["auto"]) = Field(AUTO, description=(
        "The scanner's amplitude unit per V^2 (e.g. 4000 for amplitudes in counts of 1/4000 V^2; 1: amplitudes in "
        "V^2): amplitudes are divided by it before anything reads them. auto: V^2 unless the scan's own evidence "
        "contradicts it (surfaces brighter than any albedo allows, or darker than any); then the model does not "
        "correct the scan (status unserved) and its fused depths are still written. Fusion, unwrapping and the "
        "consistency test need no unit: they use the noise law each scan measures."))
    # The sensor's depth noise over the noise model's and each frequency's depth offset relative to the highest
    # [m] (from a sensor profile): the fused depth's weights, sds and offsets. None: no offsets.
    noise_scale: Annotated[float, Field(ge=NOISE_SCALE_BOUNDS[0], le=NOISE_SCALE_BOUNDS[1])] = 1.0
    frequency_offsets_m: tuple[Annotated[float, Field(ge=-1, le=1)], ...] | None = None
    # Whether those offsets are what is left once the integration window's leakage is removed (the profile's
    # window_leakage_removed); None: measured on the depths as they are.
    window_leakage_removed: StrictBool | None = None
    baseline: Baseline = Field(Baseline.FUSED, description=(
        "What the valid pixels the model does not correct get: fused, their frequencies' depths fused by inverse "
        "variance where they agree within noise (about 0.7 of the highest frequency's noise); raw, the highest "
        "frequency's depth as measured."))
    tile_pixels: Annotated[int, Field(ge=1, le=MAX_TILE_PIXELS, strict=True)] = 262_144
    # Above this share of invalid pixels a scan is 'degraded', not 'corrected': past half the map the
    # outputs describe the sensor setup (gain, saturation level, range) more than the scene, and a batch
    # should say so rather than report success. It only names how a scan ended, never changes a pixel.
    max_invalid_share: Annotated[float, Field(ge=0, le=1, strict=True)] = Field(0.5, description=(
        "A scan with more invalid pixels (not finite, no return, saturated, inconsistent) than this share is "
        "'degraded'."))
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
        for name, neutral in (("noise_scale", 1.0), ("frequency_offsets_m", None), ("window_leakage_removed", None)):
            if pixels[name] == neutral:  # the noise model's noise, no offsets: as before they existed
                del pixels[name]
        return hashlib.sha256(json.dumps(pixels, sort_keys=True).encode()).hexdigest()

    @property
    def self_calibrating(self) -> bool:
        """Whether each scan estimates its own footprint (``footprint_area_m2`` = "auto")."""
        return self.footprint_area_m2 == AUTO

    @classmethod
    def from_cli(cls, gate: str = "geometry", min_bias_mm: float | None = None,
                 footprint_area_m2: float | str | None = None, max_invalid_share: float | None = None,
                 sensor_profile: dict[str, object] | None = None,
                 amplitude_scale: float | str | None = None, baseline: str | None = None) -> CorrectionOptions:
        """The options of ``mpi-lidar correct`` and of the correction flow, in their units; None keeps a default.

        ``min_bias_mm`` is the geometry gate's threshold in millimetres (``min_multipath_bias_m`` x 1000);
        ``footprint_area_m2`` a number or "auto"; ``sensor_profile`` the options a sensor profile sets
        (:meth:`mpi_lidar.calibration.profile.SensorProfile.options`), which the other arguments override.
        Out-of-range values are refused with one line.
        """
        given = {"gate": gate, "min_bias_mm": min_bias_mm,
                 "footprint_area_m2": _positive_or_auto("footprint_area_m2", footprint_area_m2,
                                                        "square metres (e.g. 0.02)"),
                 "max_invalid_share": max_invalid_share,
                 "amplitude_scale": _positive_or_auto("amplitude_scale", amplitude_scale, "units per V^2 (e.g. 4000)"),
                 "baseline": baseline}
        overrides = {**(sensor_profile or {}),
                     **{option.field: option.to_field(value) for option in USER_OPTIONS
                        if (value := given[option.name]) is not None}}
        try:
            return cls(**overrides)
        except ValidationError as exc:
            problems = describe_validation_error(exc, "options", shown=None, verbatim=True)
            raise MpiLidarError(f"invalid correction options ({problems})") from None


@dataclass(frozen=True)
class UserOption:
    """A field of an options model that a user sets (:class:`CorrectionOptions`, and the batch's
    :class:`~mpi_lidar.workflows.batch_options.BatchOptions`): the option :attr:`flag` of ``mpi-lidar correct``
    and the parameter ``name`` of the correction flow (and of :meth:`CorrectionOptions.from_cli`).

    Its help is the field's description, followed by ``[unit]`` where one is given. ``per_field_unit``: the
    option's value per unit of the field's (1e3 mm per m), 1 where both are in one unit. ``profile_sets``: a
    sensor profile (``--sensor``) sets the field too, and the option overrides the profile's value. An option of
    a number defaults to None: the field's default (or the profile's) applies.
    """

    field: str
    name: str
    unit: str = ""
    per_field_unit: float = 1.0
    metavar: str | None = None
    profile_sets: bool = False
    spelling: str | None = None  # the option where it is not --<name with dashes>

    @property
    def flag(self) -> str:
        """The command line's option: ``--min-bias-mm`` for ``min_bias_mm``."""
        return self.spelling or f"--{self.name.replace('_', '-')}"

    def help_text(self, model: type[BaseModel]) -> str:
        """The option's help: the field's description in ``model``, then the option's unit in brackets."""
        description = model.model_fields[self.field].description or ""
        return f"{description} [{self.unit}]" if self.unit else description

    def default_said(self, model: type[BaseModel]) -> str:
        """The default the option's None stands for, as help says it: the field's in ``model``, in the option's
        unit, or a sensor profile's."""
        default = model.model_fields[self.field].default
        default = getattr(default, "value", default)  # an enum's member as its value
        number = isinstance(default, int | float) and not isinstance(default, bool)
        said = f"{default * self.per_field_unit:g}" if number else str(default)
        return f"the --sensor profile's, else {said}" if self.profile_sets else said

    def to_field(self, value: object) -> object:
        """The option's value in the field's unit."""
        if self.per_field_unit == 1 or not isinstance(value, int | float):
            return value
        return value / self.per_field_unit


# The fields a user sets, in the order of their options in `mpi-lidar correct --help`.
USER_OPTIONS: Final = (
    UserOption("gate", "gate"),
    UserOption("min_multipath_bias_m", "min_bias_mm", unit="mm", per_field_unit=1e3),
    UserOption("footprint_area_m2", "footprint_area_m2", unit="m^2", metavar="auto|A", profile_sets=True),
    UserOption("amplitude_scale", "amplitude_scale", metavar="auto|N", profile_sets=True),
    UserOption("baseline", "baseline"),
    UserOption("max_invalid_share", "max_invalid_share"),
)


# The physical bounds of the options that also take "auto": (lowest, highest, whether the lowest is allowed).
_AUTO_BOUNDS = {"footprint_area_m2": (0.0, MAX_FOOTPRINT_AREA_M2, False),
                "amplitude_scale": (*AMPLITUDE_SCALE_BOUNDS, True)}


def _positive_or_auto(name: str, value: float | str | None, unit: str) -> float | str | None:
    """An option given on a command line or in a flow parameter: "auto", a number within its physical bounds
    (:data:`_AUTO_BOUNDS`), or None. A boolean is no number."""
    if value is None:
        return None
    if isinstance(value, str) and value.strip().lower() == AUTO:
        return AUTO
    try:
        number = float("nan") if isinstance(value, bool) else float(value)
    except (TypeError, ValueError, OverflowError):
        number = float("nan")
    low, high, low_allowed = _AUTO_BOUNDS.get(name, (0.0, np.inf, False))
    if not np.isfinite(number) or number < low or (number == low and not low_allowed) or number > high:
        bounds = f"{'[' if low_allowed else '('}{low:g}, {high:g}]"
        raise MpiLidarError(f"{name} must be 'auto' or a number of {unit} in {bounds} (its physical bounds, "
                            f"docs/reference/configuration.md), got {value!r}")
    return number
