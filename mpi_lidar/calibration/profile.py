"""A sensor profile (``sensor.toml``): what correction needs to know of one sensor, in one small file.

``mpi-lidar calibrate`` writes it from scans of that sensor (the footprint they measure, pooled, and what their
flat surfaces say of the amplitude unit, the noise and the frequencies' depth offsets); ``mpi-lidar correct
--sensor sensor.toml`` reads it, and ``mpi-lidar simulate/pipeline --sensor sensor.toml`` simulates that
sensor (its frequencies, noise scale and working range) to train a model for it. Besides the footprint it holds
the validity thresholds that depend on the sensor's gain (saturation, no return). A profile looks like::

    schema = "mpi-lidar/sensor@1"
    footprint_area_m2 = 0.0231
    saturation_amplitude_v2 = 0.7176    # optional: else each scan's own plateau of clipped amplitudes
    min_amplitude_sigmas = 5.0
    amplitude_scale = 4000.0            # the scanner's amplitude unit per V^2 (1: V^2)
    frequencies_hz = [12500000.0, 18750000.0, 25000000.0, 31250000.0]
    noise_scale = 1.02                  # its depth noise over the simulator's noise model
    range_m = [0.6, 7.5]                # the depths its scans hold (1st-99th percentile)
    frequency_offsets_m = [-0.00058, -0.00025, -0.00001, 0.0]
    speed_of_light_m_per_s = 299792458.0  # its scans' phase-to-range c: each frequency wraps at c / 2f

    [calibration]        # how the footprint was measured (written by mpi-lidar calibrate; optional)
    sigma_m2 = 0.0012
    ...
"""

from __future__ import annotations

import hashlib
import json
import tomllib
from pathlib import Path
from typing import Annotated, Final, Literal, TypedDict

from pydantic import BaseModel, ConfigDict, Field, StrictBool, ValidationError, model_validator

from mpi_lidar.config import describe_validation_error
from mpi_lidar.correction.footprint import FootprintEstimate
from mpi_lidar.correction.options import (
    AMPLITUDE_SCALE_BOUNDS,
    MAX_AMPLITUDE_V2,
    MAX_DEPTH_M,
    MAX_FOOTPRINT_AREA_M2,
    MAX_SIGMAS,
    NOISE_SCALE_BOUNDS,
    CorrectionOptions,
)
from mpi_lidar.errors import MpiLidarError
from mpi_lidar.learning.model import CARD_FILE, read_card
from mpi_lidar.locations import location
from mpi_lidar.safe_files import read_small_text
from mpi_lidar.scans.scan import SPEED_OF_LIGHT_BOUNDS_M_PER_S
from mpi_lidar.storage.atomic import atomic_path

PROFILE_SCHEMA: Final = "mpi-lidar/sensor@1"
FREQUENCY_BOUNDS_HZ = (1e3, 1e10)  # AMCW modulation: a kilohertz to ten gigahertz
MAX_FREQUENCIES = 64
MAX_OFFSET_M = 1.0  # a frequency's depth offset relative to the highest: millimetres, never a metre
Frequency = Annotated[float, Field(ge=FREQUENCY_BOUNDS_HZ[0], le=FREQUENCY_BOUNDS_HZ[1], strict=True)]
Depth = Annotated[float, Field(gt=0, le=MAX_DEPTH_M, strict=True)]
Offset = Annotated[float, Field(ge=-MAX_OFFSET_M, le=MAX_OFFSET_M, strict=True)]
_DEFAULTS = CorrectionOptions()
# A model for a sensor is trained on its working range widened by this share at either end: the scans of
# tomorrow reach a little nearer and farther than those it was calibrated on.
RANGE_MARGIN = 0.15


# The fields of a profile that hold one value per frequency, in the order of its scans' frequencies: where the
# profile meets a model or a scan each must have one value per frequency (check_profile_frequencies).
PER_FREQUENCY_FIELDS = ("frequencies_hz", "frequency_offsets_m")


class SensorProfile(BaseModel):
    """One sensor's footprint [m^2], validity thresholds [V^2, 1] and amplitude unit [units/V^2], with how the
    footprint was measured; optionally its frequencies [Hz], noise scale [1], working range [m] and the
    frequencies' depth offsets relative to the highest [m], which simulating it for a model of its own uses, and
    the speed of light its scans convert phase to range with [m/s]."""

    model_config = ConfigDict(frozen=True, extra="forbid", allow_inf_nan=False)

    schema_: Literal["mpi-lidar/sensor@1"] = Field(PROFILE_SCHEMA, alias="schema")
    # Every number within its physical bounds (docs/reference/configuration.md, "Physical bounds"), strictly a
    # number: TOML's true is no square metre.
    footprint_area_m2: Annotated[float, Field(gt=0, le=MAX_FOOTPRINT_AREA_M2, strict=True)]
    # None (or absent): each scan's own plateau of clipped amplitudes, if it has one.
    saturation_amplitude_v2: Annotated[float, Field(gt=0, le=MAX_AMPLITUDE_V2, strict=True)] | None = (
        _DEFAULTS.saturation_amplitude_v2)
    min_amplitude_sigmas: Annotated[float, Field(ge=0, le=MAX_SIGMAS, strict=True)] = _DEFAULTS.min_amplitude_sigmas
    amplitude_scale: Annotated[float, Field(ge=AMPLITUDE_SCALE_BOUNDS[0], le=AMPLITUDE_SCALE_BOUNDS[1],
                                            strict=True)] = 1.0  # V^2
    frequencies_hz: Annotated[tuple[Frequency, ...], Field(min_length=1, max_length=MAX_FREQUENCIES)] | None = None
    # The speed of light its scans convert phase to range with [m/s] (each scan carries its own; correction reads
    # the scan's): calibrate records it where its scans agree. None: not recorded.
    speed_of_light_m_per_s: Annotated[float, Field(ge=SPEED_OF_LIGHT_BOUNDS_M_PER_S[0],
                                                   le=SPEED_OF_LIGHT_BOUNDS_M_PER_S[1], strict=True)] | None = None
    noise_scale: Annotated[float, Field(ge=NOISE_SCALE_BOUNDS[0], le=NOISE_SCALE_BOUNDS[1], strict=True)] | None = None
    range_m: tuple[Depth, Depth] | None = None
    frequency_offsets_m: Annotated[tuple[Offset, ...], Field(max_length=MAX_FREQUENCIES)] | None = None
    # Whether the offsets are those left once the integration window's leakage is removed from each frequency's
    # depth (the sensor has the leakage); None, as in profiles written before it existed: measured as they are.
    window_leakage_removed: StrictBool | None = None
    calibration: dict[str, str | int | float | bool | list[str] | None] | None = None

    @model_validator(mode="after")
    def _consistent(self) -> SensorProfile:
        if self.range_m is not None and not self.range_m[0] < self.range_m[1]:
            raise ValueError(f"range_m must be [near, far] with near < far [m], got {list(self.range_m)}")
        if self.frequencies_hz is not None and len(set(self.frequencies_hz)) != len(self.frequencies_hz):
            raise ValueError(f"frequencies_hz has duplicates: {list(self.frequencies_hz)}")
        if (self.frequencies_hz is not None and self.frequency_offsets_m is not None
                and len(self.frequency_offsets_m) != len(self.frequencies_hz)):
            raise ValueError(f"frequency_offsets_m has {len(self.frequency_offsets_m)} values for "
                             f"{len(self.frequencies_hz)} frequencies_hz; give one per frequency")
        return self

    def options(self) -> dict[str, float | None]:
        """The correction options this profile sets (:meth:`CorrectionOptions.from_cli`)."""
        return {"footprint_area_m2": self.footprint_area_m2, "saturation_amplitude_v2": self.saturation_amplitude_v2,
                "min_amplitude_sigmas": self.min_amplitude_sigmas, "amplitude_scale": self.amplitude_scale}

    def noise_options(self) -> dict[str, object]:
        """The correction options of this profile's measured noise (the fused depth's weights and offsets)."""
        measured = {"noise_scale": self.noise_scale, "frequency_offsets_m": self.frequency_offsets_m,
                    "window_leakage_removed": self.window_leakage_removed if self.frequency_offsets_m else None}
        return {key: value for key, value in measured.items() if value is not None}

    def simulation(self) -> dict[str, object]:
        """The configuration sections (:meth:`mpi_lidar.config.Config.replace`) that simulate this sensor: its
        frequencies, its noise scale and, log-uniformly, its working range widened by 15 % at either end."""
        sections: dict[str, object] = {}
        if self.frequencies_hz is not None:
            sections["frequencies_hz"] = tuple(self.frequencies_hz)
        if self.noise_scale is not None:
            sections["simulator"] = {"noise_scale": self.noise_scale}
        if self.range_m is not None:
            near, far = self.range_m
            sections["prior"] = {"d_as_m": (near * (1 - RANGE_MARGIN), far * (1 + RANGE_MARGIN)),
                                 "d_as_distribution": "log_uniform"}
        return sections

    def record(self) -> dict[str, object]:
        """What a corrected output records of the profile: its values and a hash of them."""
        data = self.model_dump(by_alias=True)
        return {**data, "sha256": hashlib.sha256(json.dumps(data, sort_keys=True).encode()).hexdigest()}

    @classmethod
    def from_estimate(cls, estimate: FootprintEstimate, sources: list[str], scans: list[str] | None = None,
                      **measured: object) -> SensorProfile:
        """The profile of a pooled footprint estimate.

        Parameters
        ----------
        estimate : FootprintEstimate
            The footprint pooled over the scans (its area [m^2] and how it was measured).
        sources : list[str]
            The scans' paths, recorded in ``calibration.sources``.
        scans : list[str] | None
            What each scan measured, a line each, recorded in ``calibration.scans``.
        **measured : object
            The other fields, in their units ([V^2], [1], [Hz], [m]); None leaves a field out.

        Returns
        -------
        SensorProfile
            The validated profile.
        """
        given = {key: value for key, value in measured.items() if value is not None}
        return cls.model_validate({"footprint_area_m2": estimate.area_m2, **given,
                                   "calibration": {**{k: v for k, v in estimate.to_dict().items() if k != "area_m2"},
                                                   "sources": sources,
                                                   **({"scans": scans} if scans is not None else {})}})


def read_profile(path: str | Path) -> SensorProfile:
    """Read and check a sensor profile; every problem is one line naming the file.

    Parameters
    ----------
    path : str | Path
        The profile (``sensor.toml``): a regular UTF-8 file of at most 1 MiB.

    Returns
    -------
    SensorProfile
        The profile, each number within its physical bounds.

    Raises
    ------
    MpiLidarError
        Where the file is missing, not TOML, or not a valid profile.
    """
    path = Path(path)
    if not path.exists() and not path.is_symlink():
        raise MpiLidarError(f"sensor profile {path} does not exist; write one with mpi-lidar calibrate")
    text = read_small_text(path, "sensor profile", kind="TOML")  # a regular file of at most 1 MiB, UTF-8
    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise MpiLidarError(f"sensor profile {path} is not valid TOML ({exc}); fix or rewrite it") from None
    try:
        return SensorProfile.model_validate(data)
    except ValidationError as exc:
        problems = describe_validation_error(exc, "profile", shown=None, verbatim=True)
        raise MpiLidarError(f"sensor profile {path} is invalid ({problems})") from None


class ProfileOptions(TypedDict, total=False):
    """The :meth:`CorrectionOptions.from_cli` arguments a sensor profile sets."""

    sensor_profile: dict[str, object]


def check_profile_frequencies(profile: SensorProfile, frequencies_hz: tuple[float, ...], where: str,
                              path: str | Path) -> None:
    """Refuse a profile measured at other frequencies than ``frequencies_hz`` [Hz] (those of ``where``: a model,
    whose scans share them), or whose per-frequency fields (:data:`PER_FREQUENCY_FIELDS`) do not give one value
    per frequency, with one line."""
    mhz = ", ".join(f"{f / 1e6:g}" for f in frequencies_hz) + " MHz"
    if profile.frequencies_hz is not None and tuple(float(f) for f in profile.frequencies_hz) != tuple(
            float(f) for f in frequencies_hz):
        given = ", ".join(f"{f / 1e6:g}" for f in profile.frequencies_hz) + " MHz"
        raise MpiLidarError(f"sensor profile {path} was calibrated at {given}, but {where} is at {mhz}; calibrate "
                            "the sensor at the scans' frequencies (mpi-lidar calibrate)")
    for name in PER_FREQUENCY_FIELDS:
        values = getattr(profile, name)
        if values is not None and len(values) != len(frequencies_hz):
            raise MpiLidarError(f"sensor profile {path} gives {len(values)} {name} for the "
                                f"{len(frequencies_hz)} frequencies of {where} ({mhz}); give one per frequency, or "
                                "calibrate the sensor again")


def profile_options(path: str | Path | None, model_dir: str | Path | None = None) -> ProfileOptions:
    """The :meth:`CorrectionOptions.from_cli` arguments of a sensor profile.

    Parameters
    ----------
    path : str | Path | None
        The profile (:func:`read_profile`); None: no profile.
    model_dir : str | Path | None
        The model it corrects with: the profile's frequencies and offsets must be the model's (whose scans share
        its frequencies; :func:`check_profile_frequencies`). None, or a model without a readable card: not checked
        here (loading the model says what is wrong with it).

    Returns
    -------
    ProfileOptions
        ``sensor_profile``: the options it sets (footprint [m^2], thresholds [V^2, 1], amplitude scale
        [units/V^2], measured noise [1] and offsets [m]) and its hash; empty for None.
    """
    if path is None:
        return {}
    profile = read_profile(path)
    if model_dir is not None:
        try:
            card = read_card(str(location(model_dir) / CARD_FILE))  # a URL stays whole
        except MpiLidarError:
            card = None
        if card is not None:
            check_profile_frequencies(profile, card.frequencies_hz, f"the model {model_dir}", path)
    return {"sensor_profile": {**profile.options(), **profile.noise_options(),
                               "sensor_profile_sha256": str(profile.record()["sha256"])}}


def write_profile(profile: SensorProfile, path: str | Path) -> Path:
    """Write a profile as TOML, atomically; an existing file is refused, never replaced.

    Parameters
    ----------
    profile : SensorProfile
        The profile.
    path : str | Path
        Where to write it (``sensor.toml``); it must not exist.

    Returns
    -------
    Path
        ``path``.
    """
    lines = ["# mpi-lidar sensor profile: written by `mpi-lidar calibrate`, read by `mpi-lidar correct --sensor`.",
             f"schema = {_toml(PROFILE_SCHEMA)}"]
    lines += [f"{key} = {_toml(value)}" for key, value in profile.options().items() if value is not None]
    measured = {"frequencies_hz": profile.frequencies_hz, "noise_scale": profile.noise_scale,
                "range_m": profile.range_m, "frequency_offsets_m": profile.frequency_offsets_m,
                "window_leakage_removed": profile.window_leakage_removed,
                "speed_of_light_m_per_s": profile.speed_of_light_m_per_s}
    lines += [f"{key} = {_toml(value)}" for key, value in measured.items() if value is not None]
    if profile.calibration:
        lines += ["", "[calibration]"]
        lines += [f"{key} = {_toml(value)}" for key, value in profile.calibration.items() if value is not None]
    with atomic_path(path, what="sensor profile") as staging:
        staging.write_text("\n".join(lines) + "\n")
    return Path(path)


def _toml(value: object) -> str:
    """A TOML value: JSON's strings, numbers, booleans and arrays of them are TOML too."""
    if isinstance(value, float):
        return repr(value)
    if isinstance(value, str):
        # TOML holds UTF-8 only: a path's byte that is not UTF-8 (a lone surrogate) is written as \xff; characters
        # past U+FFFF as they are (JSON would escape them as surrogate pairs, which TOML refuses), DEL escaped.
        text = value.encode("utf-8", "surrogateescape").decode("utf-8", "backslashreplace")
        return json.dumps(text, ensure_ascii=False).replace("\x7f", "\\u007f")
    if isinstance(value, tuple | list):
        return "[" + ", ".join(_toml(item) for item in value) + "]"
    return json.dumps(value)
