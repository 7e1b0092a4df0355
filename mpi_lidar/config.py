"""Configuration: frozen pydantic models loaded from TOML, with a stable hash.

Every value of the paper's Table I is a field of :class:`SensorConfig`, its unit in its name. A
:class:`Config` bundles the sensor, the modulation frequencies, the scene-parameter prior, the simulator
options and the sampling plan; :func:`config_sha256` identifies it, so that a dataset, a model card and a
correction run can tell whether they were made from the same configuration.
"""

from __future__ import annotations

import hashlib
import json
import math
import tomllib
from pathlib import Path
from typing import Annotated, Literal

from pydantic import (
    BaseModel,
    ConfigDict,
    Field,
    SerializerFunctionWrapHandler,
    StrictBool,
    ValidationError,
    field_validator,
    model_serializer,
    model_validator,
)

from mpi_lidar.constants import (
    TABLE_BOLTZMANN_J_PER_K,
    TABLE_ELECTRON_CHARGE_C,
    TABLE_PLANCK_J_S,
    TABLE_SPEED_OF_LIGHT_M_PER_S,
)
from mpi_lidar.errors import ConfigError
from mpi_lidar.safe_files import read_small_text
from mpi_lidar.timing import whole_cycle_bins

PAPER_FREQUENCIES_HZ = (12.5e6, 18.75e6, 25e6, 31.25e6)
PAPER_SAMPLES = 1_338_670

# Bounds that keep a configuration within what one machine can hold; a value past them is a typo or a unit
# mistake, and is refused before anything is allocated or written.
MAX_SAMPLES = 1_000_000_000
MAX_CHUNK_ROWS = 10_000_000
MAX_CHUNKS = 1_000_000
MAX_BINS = 1_000_000  # time bins per integration window: the waveform simulator holds rows x bins values

# The largest geometric coupling kappa a prior may draw: a facing surface that returns this many times the light
# a white one at its distance would; the tightest rendered corners reach about 2.
MAX_COUPLING = 10.0

# Numbers are strict: TOML's true is no number of seconds, and "1e-6" no integration time.
Number = Annotated[float, Field(strict=True)]
NonNegative = Annotated[float, Field(ge=0, strict=True)]
Positive = Annotated[float, Field(gt=0, strict=True)]
Unit = Annotated[float, Field(ge=0, le=1, strict=True)]
Interval = tuple[Number, Number]


class _Frozen(BaseModel):
    model_config = ConfigDict(frozen=True, extra="forbid", allow_inf_nan=False)


class SensorConfig(_Frozen):
    """The AMCW coaxial scanning LiDAR of Table I, plus the integration time of section IV.B.

    The physical constants (speed of light, Planck, electron charge, Boltzmann) default to the table's own
    rounded values, ``mpi_lidar.constants.TABLE_*``, not to CODATA: the hash and the datasets depend on them.
    """

    gamma_r_v2: Positive = 0.1794
    modulation_contrast: Annotated[float, Field(gt=0, le=1, strict=True)] = 1.0
    speed_of_light_m_per_s: Positive = TABLE_SPEED_OF_LIGHT_M_PER_S
    demodulation_amplitude_v: Positive = 0.4785
    tia_gain_v_per_a: Positive = 50e3
    transit_time_s: Positive = 6e-9
    integration_time_s: Positive = 16e-6
    wavelength_m: Positive = 852e-9
    planck_j_s: Positive = TABLE_PLANCK_J_S
    quantum_efficiency: Annotated[float, Field(gt=0, le=1, strict=True)] = 0.67
    avalanche_gain: Annotated[float, Field(ge=1, strict=True)] = 50.0
    excess_noise_factor: Annotated[float, Field(ge=1, strict=True)] = 4.862
    electron_charge_c: Positive = TABLE_ELECTRON_CHARGE_C
    apd_area_m2: NonNegative = 0.7854e-6
    dark_current_fom_a_per_m2: NonNegative = 1e-5
    temperature_k: Positive = 297.0
    bandgap_ev: Positive = 1.1116
    boltzmann_j_per_k: Positive = TABLE_BOLTZMANN_J_PER_K
    bandwidth_hz: Positive = 50e6
    tia_noise_psd_a2_per_hz: NonNegative = 4.314e-24
    load_resistance_ohm: Positive = 50.0

    @model_validator(mode="after")
    def _integration_spans_bins(self) -> SensorConfig:
        if self.integration_time_s < 2 * self.transit_time_s:
            raise ValueError("integration_time_s must span at least two transit-time bins")
        bins = self.integration_time_s / self.transit_time_s
        if bins > MAX_BINS:
            raise ValueError(f"integration_time_s / transit_time_s is {bins:.3g} time bins, more than {MAX_BINS:,}; "
                             "check the units of both (seconds)")
        return self


class PriorConfig(_Frozen):
    """How scene parameters are drawn.

    ``reciprocal`` (default): surface albedos a, b ~ U(albedo), coupling kappa ~ U(coupling),
    rho_SAS = rho_SAB = rho_BAS = a and rho_ABA = kappa * b, kappa drawn as ``coupling_distribution`` says:
    ``uniform`` (default) U(coupling), or ``log_uniform`` over it (as many rows in every octave of kappa, so that
    the weak couplings most pixels of a scene have and the strong ones of a tight corner are both learned; its
    low end must be positive). kappa is the geometric coupling of the equivalent facing surface and may exceed 1
    (up to :data:`MAX_COUPLING`): a corner's pixel near the edge sees more of its partner than a facing white
    surface at d_AB would give it. ``independent``: the four BRDF values are
    independent U(rho). ``explicit``: each BRDF value has its own range (rho_sas, rho_sab, rho_aba,
    rho_bas). All schemes draw d_AB ~ U(d_ab_m) and d_AS from ``d_as_m`` as ``d_as_distribution`` says:
    ``uniform`` (default) U(d_as_m), or ``log_uniform``, density 1 / (d ln(high / low)), which puts as many rows
    in every octave of range (0.5-1, 1-2, 2-4, 4-8 m) so that a wide range is learned at its near and its far
    end alike. A share ``no_multipath_fraction`` of the rows (drawn independently per row) gets rho_ABA = 0:
    surfaces with no partner, as most of a real scene is (the paper's prior has multipath in every row: 0).
    """

    scheme: Literal["reciprocal", "independent", "explicit"] = "reciprocal"
    d_as_m: Interval = (1.4, 2.4)
    d_as_distribution: Literal["uniform", "log_uniform"] = "uniform"
    d_ab_m: Interval = (0.0, 0.15)
    albedo: Interval = (0.14, 1.0)
    coupling: Interval = (0.0, 1.0)
    coupling_distribution: Literal["uniform", "log_uniform"] = "uniform"
    rho: Interval = (0.0, 1.0)
    rho_sas: Interval = (0.0, 1.0)
    rho_sab: Interval = (0.0, 1.0)
    rho_aba: Interval = (0.0, 1.0)
    rho_bas: Interval = (0.0, 1.0)
    no_multipath_fraction: Unit = 0.0

    @model_serializer(mode="wrap")
    def _omit_paper_default(self, handler: SerializerFunctionWrapHandler) -> dict[str, object]:
        # At their defaults these fields are left out, so configs, dataset stores and model cards made before
        # they existed keep their hash and their bytes.
        data = handler(self)
        if self.no_multipath_fraction == 0.0:
            data.pop("no_multipath_fraction", None)
        if self.d_as_distribution == "uniform":
            data.pop("d_as_distribution", None)
        if self.coupling_distribution == "uniform":
            data.pop("coupling_distribution", None)
        return data

    @field_validator("d_as_m", "d_ab_m", "albedo", "coupling", "rho", "rho_sas", "rho_sab", "rho_aba", "rho_bas")
    @classmethod
    def _ordered_interval(cls, value: Interval) -> Interval:
        low, high = value
        if not (math.isfinite(low) and math.isfinite(high)) or low > high:
            raise ValueError(f"expected [low, high] with low <= high, got {list(value)}")
        return value

    @model_validator(mode="after")
    def _physical_ranges(self) -> PriorConfig:
        if self.d_as_m[0] <= 0:
            # A log-uniform d_AS needs it as much: ln(0) has no value.
            raise ValueError(f"d_as_m must be positive distances, got {list(self.d_as_m)}"
                             + (" (a log-uniform d_as_distribution needs low > 0)"
                                if self.d_as_distribution == "log_uniform" else ""))
        if self.d_ab_m[0] < 0:
            raise ValueError(f"d_ab_m must be non-negative distances, got {list(self.d_ab_m)}")
        for name in ("albedo", "rho", "rho_sas", "rho_sab", "rho_aba", "rho_bas"):
            low, high = getattr(self, name)
            if low < 0 or high > 1:
                raise ValueError(f"{name} must lie in [0, 1] (a reflectance), got {[low, high]}")
        low, high = self.coupling
        if low < 0 or high > MAX_COUPLING:
            raise ValueError(f"coupling must lie in [0, {MAX_COUPLING:g}] (a geometric coupling), got {[low, high]}")
        if self.coupling_distribution == "log_uniform" and low <= 0:
            raise ValueError(f"a log-uniform coupling_distribution needs coupling low > 0, got {[low, high]}")
        return self


# The default prior: the sensor's working range, 0.5 m to the 12.5 MHz unambiguous range (12 m; a white
# surface still returns there at Table I's gain), log-uniform so that every octave of range gets as many rows.
# A PriorConfig's own defaults stay the paper's 1.4-2.4 m, uniform (the ``paper`` preset): configs stored
# before this default existed name their d_as_m and read back as they were written.
WORKING_RANGE_PRIOR = PriorConfig(d_as_m=(0.5, 12.0), d_as_distribution="log_uniform")
# The working range and the multipath the geometry stage measures on rendered corners of 60-120 degrees at
# 0.5-12 m where the gate asks for correction (docs/results/prior.md: rho_ABA up to about 2, d_AB up to about
# 0.58 m at their 99.9 % quantiles), coupling log-uniform so that every octave of its strength gets as many
# rows. Not the default: a model trained on it needs about 3x the trees (3x the inference time) and loses
# accuracy inside the paper's multipath range (docs/results/prior.md), so it is the ``wide`` preset.
WIDE_MULTIPATH_PRIOR = PriorConfig(d_as_m=(0.5, 12.0), d_as_distribution="log_uniform", d_ab_m=(0.0, 0.6),
                                   coupling=(0.01, 2.0), coupling_distribution="log_uniform")


class SimulatorConfig(_Frozen):
    """Simulator fidelity and the noise terms the paper leaves open (all default 0)."""

    fidelity: Literal["moment", "waveform"] = "moment"
    noise_scale: Annotated[float, Field(ge=0, le=100, strict=True)] = 1.0
    round_photons: StrictBool = True
    whole_cycles: StrictBool = False
    background_mean_electrons: Annotated[float, Field(ge=0, le=1e9, strict=True)] = 0.0
    background_std_electrons: Annotated[float, Field(ge=0, le=1e9, strict=True)] = 0.0
    tia_noise_mean_electrons: Annotated[float, Field(ge=-1e9, le=1e9, strict=True)] = 0.0
    random_noise_std_v: Annotated[float, Field(ge=0, le=100, strict=True)] = 0.0


class DatasetConfig(_Frozen):
    """The sampling plan: how many rows, in chunks of how many, from which seed, and the test share."""

    samples: Annotated[int, Field(ge=1, le=MAX_SAMPLES, strict=True)] = 20_000
    chunk_rows: Annotated[int, Field(ge=1, le=MAX_CHUNK_ROWS, strict=True)] = 5_000
    seed: Annotated[int, Field(ge=0, strict=True)] = 20260101
    test_fraction: Annotated[float, Field(gt=0, lt=1, strict=True)] = 0.2

    @model_validator(mode="after")
    def _chunk_fits(self) -> DatasetConfig:
        if self.chunk_rows > self.samples:
            raise ValueError(
                f"chunk_rows ({self.chunk_rows}) is larger than samples ({self.samples}); "
                "lower chunk_rows or raise samples"
            )
        chunks = -(-self.samples // self.chunk_rows)
        if chunks > MAX_CHUNKS:
            raise ValueError(f"{self.samples:,} samples in chunks of {self.chunk_rows:,} rows make {chunks:,} chunks, "
                             f"more than {MAX_CHUNKS:,}; raise chunk_rows")
        return self


class Config(_Frozen):
    """Everything that determines a simulated dataset, byte for byte."""

    sensor: SensorConfig = SensorConfig()
    frequencies_hz: tuple[Number, ...] = PAPER_FREQUENCIES_HZ
    prior: PriorConfig = WORKING_RANGE_PRIOR
    simulator: SimulatorConfig = SimulatorConfig()
    dataset: DatasetConfig = DatasetConfig()

    @model_validator(mode="after")
    def _demodulable_frequencies(self) -> Config:
        freqs = self.frequencies_hz
        if not freqs:
            raise ValueError("frequencies_hz is empty; give at least one modulation frequency")
        nyquist_hz = 1 / (2 * self.sensor.transit_time_s)
        for f in freqs:
            if not math.isfinite(f) or f <= 0:
                raise ValueError(f"frequencies_hz must be positive, got {f}")
            if f >= nyquist_hz:
                raise ValueError(
                    f"frequency {f:g} Hz cannot be demodulated: bins of {self.sensor.transit_time_s:g} s "
                    f"sample below its Nyquist rate (limit {nyquist_hz:g} Hz)"
                )
            if f * self.sensor.integration_time_s < 1:
                raise ValueError(f"frequency {f:g} Hz completes less than one cycle in the integration time")
        if len(set(freqs)) != len(freqs):
            raise ValueError(f"frequencies_hz has duplicates: {list(freqs)}")
        if self.simulator.whole_cycles:
            self._check_whole_cycle_windows()
        return self

    def _check_whole_cycle_windows(self) -> None:
        s = self.sensor
        window = round(s.integration_time_s / s.transit_time_s)
        for f in self.frequencies_hz:
            try:
                whole_cycle_bins(f, s.transit_time_s, max_bins=window)
            except ValueError:
                raise ValueError(
                    f"frequency {f:g} Hz completes no whole number of cycles within {window} bins of "
                    f"{s.transit_time_s:g} s; set simulator.whole_cycles = false or choose a commensurate frequency"
                ) from None

    def replace(self, **sections: object) -> Config:
        """A copy with whole sections or nested fields replaced, validated again.

        ``config.replace(simulator={"noise_scale": 0})`` changes one field of one section.
        """
        data = self.model_dump()
        for key, value in sections.items():
            if isinstance(value, dict) and isinstance(data.get(key), dict):
                data[key] = {**data[key], **value}
            elif isinstance(value, BaseModel):
                data[key] = value.model_dump()
            else:
                data[key] = value
        return Config.model_validate(data)


PRESETS: dict[str, dict[str, object]] = {
    "quick": {"dataset": {"samples": 20_000, "chunk_rows": 5_000}},
    "wide": {"dataset": {"samples": 20_000, "chunk_rows": 5_000}, "prior": WIDE_MULTIPATH_PRIOR.model_dump()},
    "paper": {"dataset": {"samples": PAPER_SAMPLES, "chunk_rows": 65_536, "test_fraction": 0.2},
              "prior": {"d_as_m": PriorConfig().d_as_m, "d_as_distribution": "uniform"}},
}


def preset(name: str) -> Config:
    """The named preset: ``quick`` (20,000 rows of the working range, 0.5-12 m), ``wide`` (the same on the wide
    multipath prior :data:`WIDE_MULTIPATH_PRIOR`, d_AB 0-0.6 m, coupling log-uniform 0.01-2) or ``paper``
    (1,338,670 rows of the paper's prior, d_AS 1.4-2.4 m, 80/20 split)."""
    if name not in PRESETS:
        raise ConfigError(f"unknown preset {name!r}; choose one of {', '.join(sorted(PRESETS))}")
    return Config().replace(**PRESETS[name])


def config_sha256(config: Config) -> str:
    """A stable identity: SHA-256 of the canonical JSON of every field (sorted keys, repr floats)."""
    return hashlib.sha256(config_json(config).encode()).hexdigest()


def config_json(config: Config) -> str:
    return json.dumps(config.model_dump(mode="json"), sort_keys=True, separators=(",", ":"))


def config_from_json(text: str) -> Config:
    return Config.model_validate_json(text)


def load_config(path: str | Path, base: Config | None = None) -> Config:
    """Read a TOML file whose tables (``[sensor]``, ``[prior]``, ...) override ``base`` (default: defaults).

    Only a regular file of at most :data:`mpi_lidar.safe_files.MAX_CONFIG_BYTES` is read. Raises
    :class:`ConfigError` with one line naming the file and the offending field.
    """
    path = Path(path)
    text = read_small_text(path, "config file", kind="TOML")  # a regular file of at most MAX_CONFIG_BYTES, UTF-8
    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(f"config file {path} is not valid TOML: {exc}") from None
    return validate_overrides(data, base or Config(), source=str(path))


def resolve_config(
    config_file: str | Path | None = None,
    preset_name: str = "quick",
    *,
    samples: int | None = None,
    chunk_rows: int | None = None,
    seed: int | None = None,
    fidelity: str | None = None,
) -> Config:
    """Preset, then the TOML file's tables, then the given values; validated at each step.

    Fewer ``samples`` than the chunk size shrink the chunks to fit, unless ``chunk_rows`` is given.
    """
    config = preset(preset_name)
    if config_file is not None:
        config = load_config(config_file, base=config)
    sampling: dict[str, object] = {k: v for k, v in (("samples", samples), ("chunk_rows", chunk_rows),
                                                     ("seed", seed)) if v is not None}
    if samples is not None and chunk_rows is None:
        sampling["chunk_rows"] = max(1, min(config.dataset.chunk_rows, samples))
    overrides: dict[str, object] = {"dataset": sampling} if sampling else {}
    if fidelity is not None:
        overrides["simulator"] = {"fidelity": fidelity}
    return validate_overrides(overrides, config, source="command line") if overrides else config


def validate_overrides(overrides: dict[str, object], base: Config, source: str) -> Config:
    try:
        return base.replace(**overrides)
    except ValidationError as exc:
        raise ConfigError(f"{source}: {describe_validation_error(exc)}") from None


def describe_validation_error(exc: ValidationError, root: str = "config", *, shown: int | None = 1,
                              keys: bool = False, verbatim: bool = False) -> str:
    """The problems of a pydantic error in one line, each as 'field.path: message'.

    The one formatter of the package's validation errors (configurations, correction options, sensor
    profiles, model cards). ``root`` names a problem of the whole object (an empty path). ``shown``: how many
    problems are listed (None: all, joined by "; "); with fewer, the first ones and how many more there are.
    ``verbatim``: pydantic's messages as they are; otherwise "Value error, " is dropped and an unknown field
    says to check its spelling. ``keys``: the problems of a JSON document's keys (a model card): a missing or
    unknown field as "lacks key 'a.b'" / "has unknown key 'a.b'", any other with the JSON kind of the value
    found, each problem once, "; and N more" after the first ``shown``.
    """
    problems: list[str] = []
    errors = exc.errors(include_url=False)
    for error in errors:
        where = ".".join(str(part) for part in error["loc"]) or root
        if keys:
            if error["type"] == "missing":
                problem = f"lacks key {where!r}"
            elif error["type"] == "extra_forbidden":
                problem = f"has unknown key {where!r}"
            else:
                problem = f"{where}: {error['msg']} (found {json_kind(error.get('input'))})"
            if problem not in problems:
                problems.append(problem)
            continue
        message = error["msg"]
        if not verbatim:
            message = message.removeprefix("Value error, ")
            if error["type"] == "extra_forbidden":
                message = "unknown field (check its spelling against the documented configuration)"
        problems.append(f"{where}: {message}")
    listed = problems if shown is None else problems[:shown]
    if keys:
        more = f"; and {len(problems) - len(listed)} more" if len(problems) > len(listed) else ""
        return ("; ".join(listed) + more).replace("\n", " ")
    more_count = len(errors) - len(listed)
    more = f" (and {more_count} more problem{'s' * (more_count > 1)})" if more_count else ""
    return "; ".join(listed) + more


def json_kind(value: object) -> str:
    """The JSON name of a value's kind (list, string, number, boolean, null; else its Python type's name)."""
    kinds = {list: "list", str: "string", bool: "boolean", int: "number", float: "number", type(None): "null"}
    return kinds.get(type(value), type(value).__name__)
