"""A sensor profile (``sensor.toml``): what correction needs to know of one sensor, in one small file.

``mpi-lidar calibrate`` writes it from scans of that sensor (the footprint they measure, pooled); ``mpi-lidar
correct --sensor sensor.toml`` reads it. Besides the footprint it holds the validity thresholds that depend on
the sensor's gain (saturation, no return). A profile looks like::

    schema = "mpi-lidar/sensor@1"
    footprint_area_m2 = 0.0231
    saturation_amplitude_v2 = 0.7176
    min_amplitude_sigmas = 5.0

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

from pydantic import BaseModel, ConfigDict, Field, ValidationError

from mpi_lidar.config import describe_validation_error
from mpi_lidar.correction.footprint import FootprintEstimate
from mpi_lidar.correction.options import CorrectionOptions
from mpi_lidar.errors import MpiLidarError
from mpi_lidar.storage.atomic import atomic_path

PROFILE_SCHEMA: Final = "mpi-lidar/sensor@1"
_DEFAULTS = CorrectionOptions()


class SensorProfile(BaseModel):
    """One sensor's footprint [m^2] and validity thresholds, with how the footprint was measured."""

    model_config = ConfigDict(frozen=True, extra="forbid", allow_inf_nan=False)

    schema_: Literal["mpi-lidar/sensor@1"] = Field(PROFILE_SCHEMA, alias="schema")
    footprint_area_m2: Annotated[float, Field(gt=0)]
    saturation_amplitude_v2: Annotated[float, Field(gt=0)] = _DEFAULTS.saturation_amplitude_v2
    min_amplitude_sigmas: Annotated[float, Field(ge=0)] = _DEFAULTS.min_amplitude_sigmas
    calibration: dict[str, str | int | float | bool | list[str] | None] | None = None

    def options(self) -> dict[str, float]:
        """The correction options this profile sets (:meth:`CorrectionOptions.from_cli`)."""
        return {"footprint_area_m2": self.footprint_area_m2, "saturation_amplitude_v2": self.saturation_amplitude_v2,
                "min_amplitude_sigmas": self.min_amplitude_sigmas}

    def record(self) -> dict[str, object]:
        """What a corrected output records of the profile: its values and a hash of them."""
        data = self.model_dump(by_alias=True)
        return {**data, "sha256": hashlib.sha256(json.dumps(data, sort_keys=True).encode()).hexdigest()}

    @classmethod
    def from_estimate(cls, estimate: FootprintEstimate, sources: list[str], **thresholds: float) -> SensorProfile:
        """The profile of a pooled footprint estimate over ``sources`` (the scans' paths)."""
        return cls.model_validate({"footprint_area_m2": estimate.area_m2, **thresholds,
                                   "calibration": {**{k: v for k, v in estimate.to_dict().items() if k != "area_m2"},
                                                   "sources": sources}})


def read_profile(path: str | Path) -> SensorProfile:
    """Read and check a sensor profile; every problem is one line naming the file."""
    path = Path(path)
    try:
        data = tomllib.loads(path.read_text())
    except FileNotFoundError:
        raise MpiLidarError(f"sensor profile {path} does not exist; write one with mpi-lidar calibrate") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise MpiLidarError(f"cannot read sensor profile {path}: {exc}") from None
    except tomllib.TOMLDecodeError as exc:
        raise MpiLidarError(f"sensor profile {path} is not valid TOML ({exc}); fix or rewrite it") from None
    try:
        return SensorProfile.model_validate(data)
    except ValidationError as exc:
        problems = describe_validation_error(exc, "profile", shown=None, verbatim=True)
        raise MpiLidarError(f"sensor profile {path} is invalid ({problems})") from None


class ProfileOptions(TypedDict, total=False):
    """The :meth:`CorrectionOptions.from_cli` arguments a sensor profile sets."""

    sensor_profile: dict[str, float | str]


def profile_options(path: str | Path | None) -> ProfileOptions:
    """The :meth:`CorrectionOptions.from_cli` arguments of the profile at ``path`` (none for None)."""
    if path is None:
        return {}
    profile = read_profile(path)
    return {"sensor_profile": {**profile.options(), "sensor_profile_sha256": str(profile.record()["sha256"])}}


def write_profile(profile: SensorProfile, path: str | Path) -> Path:
    """Write a profile as TOML, atomically; an existing file is refused, never replaced."""
    lines = ["# mpi-lidar sensor profile: written by `mpi-lidar calibrate`, read by `mpi-lidar correct --sensor`.",
             f"schema = {_toml(PROFILE_SCHEMA)}"]
    lines += [f"{key} = {_toml(value)}" for key, value in profile.options().items()]
    if profile.calibration:
        lines += ["", "[calibration]"]
        lines += [f"{key} = {_toml(value)}" for key, value in profile.calibration.items() if value is not None]
    with atomic_path(path, what="sensor profile") as staging:
        staging.write_text("\n".join(lines) + "\n")
    return Path(path)


def _toml(value: object) -> str:
    """A TOML value: JSON's strings, numbers, booleans and arrays of strings are TOML too."""
    if isinstance(value, float):
        return repr(value)
    return json.dumps(value)
