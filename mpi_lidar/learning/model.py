"""Model directories: ``model.ubj`` (XGBoost's own format, never pickle) and ``card.json``.

The card says what the model expects and how it was made: frequencies, raw and model feature names in
order, feature set and target mode, the dataset it learned from, its parameters, metrics and package
versions. In code it is a :class:`ModelCard`; on disk the same keys as a JSON object. Loading validates
the card and checks it against the model file; correction checks it against the data. A model directory
may be an object-store URL (``s3://bucket/models/m``): published by its card, written last
(:func:`staged_model`), and read whole into memory, never through a local copy.
"""

from __future__ import annotations

import hashlib
import json
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from importlib.metadata import version
from pathlib import Path
from tempfile import TemporaryDirectory
from typing import TYPE_CHECKING, Annotated, Literal, overload

import numpy as np
from numpy.typing import NDArray
from pydantic import BaseModel, ConfigDict, Field, PlainValidator, ValidationError, model_validator

from mpi_lidar import __version__
from mpi_lidar.config import Config, config_sha256, describe_validation_error, json_kind
from mpi_lidar.errors import MpiLidarError
from mpi_lidar.learning.features import FeatureSet, FeatureSpec, TargetMode
from mpi_lidar.learning.xgboost_import import import_xgboost
from mpi_lidar.locations import Location, location
from mpi_lidar.storage import objects
from mpi_lidar.storage.atomic import atomic_path

if TYPE_CHECKING:
    import dask.array as da
    import xgboost as xgb  # imported where a booster is loaded: importing XGBoost imports scikit-learn (~1 s)

MODEL_SCHEMA = "mpi-lidar/model@1"
MODEL_FILE = "model.ubj"
CARD_FILE = "card.json"
# Read from an object store whole, in memory: anything larger is not one of ours.
MAX_CARD_BYTES = 2**20
MAX_MODEL_BYTES = 2**30


def package_versions() -> dict[str, str]:
    names = ("xgboost-cpu", "numpy", "dask", "distributed", "optuna", "zarr", "scikit-learn")
    found = {"mpi-lidar": __version__}
    for name in names:
        try:
            found[name] = version(name)
        except Exception:  # a package that is not installed is simply not listed
            continue
    return found


def file_sha256(path: Path) -> str:
    digest = hashlib.sha256()
    with path.open("rb") as handle:
        for block in iter(lambda: handle.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()


def booster_sha256(booster: xgb.Booster) -> str:
    """SHA-256 of the booster as ``save_model`` writes it to ``model.ubj`` (UBJSON)."""
    return hashlib.sha256(booster.save_raw("ubj")).hexdigest()


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


# --- the model -----------------------------------------------------------------------------------------------


def booster_depth(booster: xgb.Booster, spec: FeatureSpec, raw: NDArray,
                  geometry: NDArray | None = None) -> NDArray[np.float64]:
    """Corrected depth [m] of raw rows (n, 2F) by a booster trained on ``spec``, in this process."""
    return depth_from_features(booster, spec, raw, spec.transform(raw, geometry))


def depth_from_features(booster: xgb.Booster, spec: FeatureSpec, raw: NDArray, features: NDArray[np.float32]
                        ) -> NDArray[np.float64]:
    """Corrected depth [m] of raw rows (n, 2F) whose model inputs ``features`` are built already
    (:meth:`FeatureSpec.transform_into`)."""
    prediction = booster.inplace_predict(features)
    return np.asarray(spec.depth(raw, prediction.astype(np.float64)))


@dataclass
class CorrectionModel:
    """A loaded, card-checked model that turns raw measurements into corrected depths."""

    booster: xgb.Booster
    card: ModelCard

    @property
    def spec(self) -> FeatureSpec:
        return self.card.spec

    def check_compatible(self, frequencies_hz: tuple[float, ...], raw_names: list[str] | tuple[str, ...],
                         source: str) -> None:
        """Refuse data whose frequencies or raw columns differ from the card's, with one clear line."""
        expected = self.card.frequencies_hz
        if tuple(float(f) for f in frequencies_hz) != expected:
            raise MpiLidarError(
                f"{source} was measured at {_mhz(frequencies_hz)} but the model expects {_mhz(expected)}; "
                "train a model for them (mpi-lidar calibrate writes them into sensor.toml, then mpi-lidar "
                "pipeline --sensor sensor.toml)"
            )
        if list(raw_names) != list(self.card.raw_feature_names):
            raise MpiLidarError(f"{source} has columns {list(raw_names)} but the model expects "
                                f"{list(self.card.raw_feature_names)}; the data and model do not match")

    @property
    def geometric(self) -> bool:
        """Whether the model needs the geometric inputs (rho_ABA, d_AB) of every pixel."""
        return self.card.geometric

    def predict_depth(self, raw: NDArray, geometry: NDArray | None = None) -> NDArray[np.float64]:
        """Corrected depth [m] for raw measurements (n, 2F) in this process (XGBoost inplace_predict).

        ``geometry`` (n, 2): geometric coupling [1] and d_AB [m] per row, required by a geometric model
        (:attr:`geometric`) and ignored by the others.
        """
        return booster_depth(self.booster, self.spec, raw, geometry)

    def depth_from_features(self, raw: NDArray, features: NDArray[np.float32]) -> NDArray[np.float64]:
        """:meth:`predict_depth` of raw rows (n, 2F) whose inputs are built already (``spec.transform_into``)."""
        return depth_from_features(self.booster, self.spec, raw, features)

    def predict_depth_dask(self, client: object, raw: da.Array, geometry: da.Array | None = None) -> da.Array:
        """Corrected depth [m] for a dask array of raw measurements, predicted on the cluster's workers."""
        import xgboost.dask as dxgb

        spec = self.spec
        prediction = dxgb.inplace_predict(client, self.booster, spec.transform(raw, geometry))
        return spec.depth(raw, prediction.astype(np.float64))


def _mhz(frequencies_hz: tuple[float, ...] | list[float]) -> str:
    return ", ".join(f"{f / 1e6:g}" for f in frequencies_hz) + " MHz"


@overload
def save_model(out_dir: Path, booster: xgb.Booster, card: ModelCard) -> Path: ...


@overload
def save_model(out_dir: str | Path, booster: xgb.Booster, card: ModelCard) -> str | Path: ...


def save_model(out_dir: str | Path, booster: xgb.Booster, card: ModelCard) -> str | Path:
    """Write model.ubj and card.json into a new directory (a path, or an object-store URL), whole or not at all.

    The saved booster carries the card's feature names (predictions are unchanged); the card written records
    the SHA-256 of the model file and this environment's package versions. An existing directory is never
    overwritten: choose a new ``out_dir`` or remove the old one. On a local file system the directory is built
    beside ``out_dir`` and renamed; in an object store it is built locally and published there
    (:func:`staged_model`).
    """
    where = location(out_dir)
    if where.is_local:
        return _save_local(where.local_path(), booster, card)
    with staged_model(where.url) as staging:
        _save_local(staging, booster, card)
    return where.url


def _save_local(out_dir: Path, booster: xgb.Booster, card: ModelCard) -> Path:
    if booster.num_features() != len(card.feature_names):
        raise MpiLidarError(f"the booster has {booster.num_features()} inputs but its card lists "
                            f"{len(card.feature_names)} features; not saving {out_dir}")
    with atomic_path(out_dir, what="model directory") as staging:
        staging.mkdir()
        named = booster.copy()
        named.feature_names = list(card.feature_names)
        named.save_model(str(staging / MODEL_FILE))
        written = card.model_copy(update={"model_sha256": file_sha256(staging / MODEL_FILE),
                                          "versions": package_versions()})
        (staging / CARD_FILE).write_text(written.to_json())
    return out_dir


@contextmanager
def staged_model(out_dir: str | Path) -> Iterator[Path]:
    """The local directory to write a model into that is to end at ``out_dir``.

    A local ``out_dir`` is given back as it is (:func:`save_model` publishes it by a rename). For an
    object-store URL, a model already there is refused before the block runs (so before a training), the
    block writes a new local directory, and when it ends without error that directory is published at
    ``out_dir``: ``model.ubj`` first, then ``card.json`` by a conditional create. A reader needs the card, so
    it sees the model whole or not at all, and of two trainings publishing at once only one succeeds. A
    ``model.ubj`` without its card (a publication killed midway) is no model and is written over.
    """
    where = location(out_dir)
    if where.is_local:
        yield where.local_path()
        return
    objects.check_writable(where)
    refuse_existing_model(where)
    with TemporaryDirectory(prefix="mpi-lidar-model-") as temporary:
        staging = Path(temporary) / "model"
        yield staging
        if not (staging / CARD_FILE).is_file():
            raise MpiLidarError(f"no model was written for {where}; nothing published")
        objects.publish_whole(staging, where, CARD_FILE)


def refuse_existing_model(where: Location) -> None:
    """Refuse an object-store location that holds anything but an unpublished ``model.ubj`` (one listing)."""
    there = objects.list_files(where)
    if set(there) - {MODEL_FILE}:
        raise MpiLidarError(f"model directory {where} already exists; choose another --out or remove it")


# The first geometric input of models trained before the equivalent rho_ABA replaced it.
EARLIER_GEOMETRIC_NAME = "geometric_coupling"


def load_model(model_dir: str | Path) -> CorrectionModel:
    """Load a model directory (a path, or an object-store URL) after checking its card: keys and types,
    schema, file hash and features. Only XGBoost's own format is read, never a pickle."""
    where = location(model_dir)
    if not where.is_local:
        return _load_from_store(where)
    model_dir = where.local_path()
    card_path, model_path = model_dir / CARD_FILE, model_dir / MODEL_FILE
    if not card_path.is_file() or not model_path.is_file():
        raise MpiLidarError(f"{model_dir} is not a model directory (needs {MODEL_FILE} and {CARD_FILE}); "
                            "train one with 'mpi-lidar train'")
    card = read_card(card_path)
    if card.model_sha256 != file_sha256(model_path):
        raise MpiLidarError(f"{model_path} does not match the hash in its card; the model directory is damaged")
    return _checked_model(_booster(str(model_path), str(model_path)), card, str(model_dir), str(card_path))


def _load_from_store(where: Location) -> CorrectionModel:
    """:func:`load_model` of a URL: the card (which publishes the model), then the model file, each read whole
    once."""
    card_at, model_at = where.joinpath(CARD_FILE), where.joinpath(MODEL_FILE)
    card_bytes = objects.read_bytes(card_at, MAX_CARD_BYTES)
    model_bytes = objects.read_bytes(model_at, MAX_MODEL_BYTES) if card_bytes is not None else None
    if card_bytes is None or model_bytes is None:
        raise MpiLidarError(f"{where} is not a published model directory (needs {MODEL_FILE} and {CARD_FILE}); "
                            "train one there with 'mpi-lidar train --out'")
    card = card_from_bytes(card_bytes, str(card_at))
    if card.model_sha256 != hashlib.sha256(model_bytes).hexdigest():
        raise MpiLidarError(f"{model_at} does not match the hash in its card; the model directory is damaged")
    return _checked_model(_booster(bytearray(model_bytes), str(model_at)), card, str(where), str(card_at))


def _booster(source: str | bytearray, name: str) -> xgb.Booster:
    """A booster from a UBJSON file's path or bytes; one line naming ``name`` where it is not one."""
    import_xgboost()  # without scikit-learn: a one-scan correction's start-up
    import xgboost as xgb

    booster = xgb.Booster()
    try:
        booster.load_model(source)
    except xgb.core.XGBoostError as exc:
        raise MpiLidarError(f"{name} is not a readable XGBoost model: {str(exc).splitlines()[0]}") from None
    except UnicodeDecodeError:  # XGBoost echoes the file's first bytes; a pickle's are not UTF-8
        raise MpiLidarError(f"{name} is not a readable XGBoost model (not UBJSON; a pickle is never "
                            "loaded)") from None
    return booster


def _checked_model(booster: xgb.Booster, card: ModelCard, model_dir: str, card_name: str) -> CorrectionModel:
    """The model, once its card's features match the booster's inputs and the feature set's."""
    names = list(card.feature_names)
    if EARLIER_GEOMETRIC_NAME in names:
        raise MpiLidarError(f"{model_dir} takes the earlier geometric input {EARLIER_GEOMETRIC_NAME!r} (the coupling "
                            "to a white partner), which correction no longer gives; retrain it with 'mpi-lidar "
                            "train' (its inputs are now the equivalent rho_ABA and d_AB)")
    booster_names = booster.feature_names  # None for models saved before names were stored
    spec = card.spec
    if (booster.num_features() != len(names) or names != spec.names or list(card.raw_feature_names) != spec.raw_names
            or (booster_names is not None and list(booster_names) != names)):
        raise MpiLidarError(f"{card_name} lists features {names} that do not match its model "
                            f"({booster.num_features()} inputs) or its feature set {card.feature_set!r}")
    return CorrectionModel(booster=booster, card=card)
