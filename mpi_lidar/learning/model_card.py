"""The model card: what a model expects and how it was made (frequencies, raw and model feature names in order,
feature set and target mode, the dataset it learned from, its parameters, metrics, uncertainty and package
versions), as :class:`ModelCard` in code and ``card.json`` on disk, and its validated reading."""

from __future__ import annotations

import json
from pathlib import Path
from typing import TYPE_CHECKING, Annotated, Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, PlainValidator, ValidationError, model_validator

from mpi_lidar.config import Config, config_sha256, describe_validation_error, json_kind
from mpi_lidar.errors import MpiLidarError
from mpi_lidar.learning.features import FeatureSet, FeatureSpec, TargetMode
from mpi_lidar.locations import location
from mpi_lidar.storage import objects

if TYPE_CHECKING:
    pass  # imported where a booster is loaded: importing XGBoost imports scikit-learn (~1 s)

MODEL_SCHEMA = "mpi-lidar/model@1"
# Read from an object store whole, in memory: anything larger is not one of ours.
MAX_CARD_BYTES = 2**20


# --- the card ------------------------------------------------------------------------------------------------


class _Part(BaseModel):
    """A part of the card with a fixed set of keys: an unknown or missing key is an error."""

    model_config = ConfigDict(frozen=True, extra="forbid")


class _Dump(BaseModel):
    """A configuration section copied into the card at training time: the keys read here are typed, the others
    are kept as written (the configuration's fields change between versions; old cards keep theirs)."""

    model_config = ConfigDict(frozen=True, extra="allow")


class PriorCard(_Dump):
    """The prior the training rows were drawn from (:class:`mpi_lidar.config.PriorConfig` as written)."""

    d_as_m: tuple[float, float]
    """Range of the true direct depth d_AS [m]: the depths the model has seen."""

    @model_validator(mode="after")
    def _ordered(self) -> PriorCard:
        if not self.d_as_m[0] <= self.d_as_m[1]:
            raise ValueError(f"d_as_m {list(self.d_as_m)} is not a (low, high) range")
        return self

    def multipath_reach(self) -> tuple[float, float] | None:
        """The largest rho_ABA [1] and d_AB [m] of the training rows' multipath, from the prior's scheme and ranges
        as written (:func:`mpi_lidar.simulation.sampling.sample_theta`); None where the card lacks them."""
        written = self.model_extra or {}
        try:
            scheme = written.get("scheme", "reciprocal")
            if scheme == "reciprocal":  # rho_ABA = coupling x the partner's albedo
                rho_aba = float(written["coupling"][1]) * float(written["albedo"][1])
            else:
                rho_aba = float(written["rho" if scheme == "independent" else "rho_aba"][1])
            return rho_aba, float(written["d_ab_m"][1])
        except (KeyError, TypeError, ValueError, IndexError):
            return None


class SimulatorCard(_Dump):
    """The simulator settings of the training rows (:class:`mpi_lidar.config.SimulatorConfig` as written)."""

    noise_scale: float


class DatasetCard(_Part):
    """The dataset the model learned from."""

    path: str
    config_sha256: str
    samples: int = Field(ge=0)
    prior: PriorCard
    simulator: SimulatorCard

    @classmethod
    def from_config(cls, config: Config, path: str = "", sha256: str | None = None,
                    samples: int | None = None) -> DatasetCard:
        """The card of a dataset made from ``config`` (``path`` empty for rows simulated in memory)."""
        return cls(path=path, config_sha256=sha256 or config_sha256(config),
                   samples=config.dataset.samples if samples is None else samples,
                   prior=PriorCard(**config.prior.model_dump(mode="json")),
                   simulator=SimulatorCard(**config.simulator.model_dump(mode="json")))


class GeometryErrorCard(_Part):
    """The error model of the synthetic geometric inputs a geometric model trained on
    (:data:`mpi_lidar.learning.features.GEOMETRY_ERROR_MODEL`)."""

    coupling_log_median: float
    coupling_log_sd: float
    d_ab_offset_m: float
    d_ab_sd_m: float


class RegionScales(_Part):
    """Factors of the uncertainty law per region of the prior (:func:`mpi_lidar.learning.error_model.
    fit_region_scales`): ``factors[i][j]`` for rows whose equivalent rho_ABA lies in bin i (lower edges
    ``rho_aba_edges`` [1], the last open) and d_AB in bin j (lower edges ``d_ab_edges_m`` [m], the last open)."""

    rho_aba_edges: tuple[float, ...] = Field(min_length=1)
    d_ab_edges_m: tuple[float, ...] = Field(min_length=1)
    factors: tuple[tuple[float, ...], ...]

    @model_validator(mode="after")
    def _shape(self) -> RegionScales:
        if len(self.factors) != len(self.rho_aba_edges) or any(len(row) != len(self.d_ab_edges_m)
                                                                 for row in self.factors):
            raise ValueError(f"factors must be {len(self.rho_aba_edges)} x {len(self.d_ab_edges_m)}, one per region")
        if any(not np.isfinite(f) or f <= 0 for row in self.factors for f in row):
            raise ValueError("factors must be positive and finite")
        return self


class UncertaintyCard(_Part):
    """The corrected depths' 1-sigma uncertainty, fitted on the validation rows of the training
    (:mod:`mpi_lidar.learning.error_model`): sigma^2 = (noise_factor sigma_fused)^2
    + (model_sd_m (|c| / reference_correction_m)^correction_exponent)^2, with sigma_fused the fused depth's sd
    under the noise model [m] and c the pixel's correction [m]."""

    noise_factor: float = Field(ge=0)
    """Multiple of the fused depth's sd, the noise the model's output keeps. [1]"""
    model_sd_m: float = Field(ge=0)
    """The model's own error at a correction of ``reference_correction_m``. [m]"""
    reference_correction_m: float = Field(gt=0)
    correction_exponent: float
    """How the model's own error grows with the size of the correction. [1]"""
    validation_rows: int = Field(ge=0)
    validation_coverage: float = Field(ge=0, le=1)
    """Share of the validation rows whose error lies within this sigma. [1]"""
    region_scales: RegionScales | None = None
    """A geometric model's factors per region of the prior (absent on cards written before them, and for models
    without geometric inputs: the law alone)."""


class MetricsCard(_Part):
    validation_mae_m: float
    """MAE of the residual or depth target on the validation rows at the best iteration. [m]"""


class TrainingCard(_Part):
    fit_rows: int = Field(ge=0)
    validation_rows: int = Field(ge=0)
    wall_s: float = Field(ge=0)
    dask_workers: int = Field(ge=0)


def _param_value(value: object) -> str | int | float | bool:
    if isinstance(value, str | int | float | bool):
        return value
    raise ValueError(f"an XGBoost parameter must be a string, number or boolean, not {type(value).__name__}")


ParamValue = Annotated[str | int | float | bool, PlainValidator(_param_value)]


class ModelCard(_Part):
    """What a model expects and how it was made; ``card.json`` holds exactly these keys.

    ``geometric`` is False and ``geometry_error_model`` absent on cards written before geometric inputs;
    ``uncertainty_model`` is absent on cards written before it was fitted, and where the training had too few
    validation rows to fit it.
    """

    card_schema: Literal["mpi-lidar/model@1"] = Field(alias="schema")
    frequencies_hz: tuple[float, ...] = Field(min_length=1)
    raw_feature_names: tuple[str, ...]
    feature_set: FeatureSet
    feature_names: tuple[str, ...]
    geometric: bool = False
    geometry_error_model: GeometryErrorCard | None = None
    uncertainty_model: UncertaintyCard | None = None
    target_mode: TargetMode
    residual_reference: str | None
    dataset: DatasetCard
    params: dict[str, ParamValue]
    num_boost_round: int = Field(ge=0)
    metrics: MetricsCard
    training: TrainingCard
    versions: dict[str, str]
    model_sha256: str = Field(pattern=r"^[0-9a-f]{64}$")

    @property
    def spec(self) -> FeatureSpec:
        return FeatureSpec(self.frequencies_hz, self.feature_set, self.target_mode, self.geometric)

    def to_json(self) -> str:
        """The card as ``card.json`` holds it (sorted keys; no ``geometry_error_model`` or ``uncertainty_model`` key
        where it has none)."""
        data = self.model_dump(mode="json", by_alias=True)
        for optional in ("geometry_error_model", "uncertainty_model"):
            if data[optional] is None:
                del data[optional]
        if data.get("uncertainty_model") and data["uncertainty_model"].get("region_scales") is None:
            del data["uncertainty_model"]["region_scales"]
        return json.dumps(data, indent=2, sort_keys=True) + "\n"


def read_card(card_path: str | Path) -> ModelCard:
    """The validated card in ``card_path`` (a path, or an object-store URL); :class:`MpiLidarError` (one line
    naming the file) if it is not one."""
    where = location(card_path)
    if not where.is_local:
        found = objects.read_bytes(where, MAX_CARD_BYTES)
        if found is None:
            raise MpiLidarError(f"{where} cannot be read: it does not exist")
        return card_from_bytes(found, str(where))
    try:
        data = where.local_path().read_bytes()
    except OSError as exc:
        raise MpiLidarError(f"{card_path} cannot be read: {exc.strerror or exc}") from None
    return card_from_bytes(data, str(card_path))


def card_from_bytes(data: bytes, name: str) -> ModelCard:
    """The validated card of ``card.json``'s bytes, read from ``name`` (for messages)."""
    try:
        text = data.decode()
        found = json.loads(text)
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise MpiLidarError(f"{name} is not valid JSON ({exc}); the model directory is damaged") from None
    if not isinstance(found, dict):
        raise MpiLidarError(f"{name} holds a JSON {json_kind(found)}, not an object; the model directory "
                            "is damaged")
    if found.get("schema") != MODEL_SCHEMA:
        raise MpiLidarError(f"{name} has schema {found.get('schema')!r}, expected {MODEL_SCHEMA!r}")
    try:
        return ModelCard.model_validate_json(text, strict=True)
    except ValidationError as exc:
        problems = describe_validation_error(exc, "the card", shown=3, keys=True)
        raise MpiLidarError(f"{name} is not a valid model card: {problems}; the model directory is damaged or "
                            "from another mpi-lidar version") from None
