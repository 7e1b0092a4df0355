"""Model directories: ``model.ubj`` (XGBoost's own format, never pickle) and ``card.json``.

The card (:mod:`mpi_lidar.learning.model_card`) says what the model expects and how it was made. Loading validates
the card and checks it against the model file; correction checks it against the data. A model directory
may be an object-store URL (``s3://bucket/models/m``): published by its card, written last
(:func:`staged_model`), and read whole into memory, never through a local copy.
"""

from __future__ import annotations

import hashlib
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from importlib.metadata import version
from pathlib import Path
from tempfile import TemporaryDirectory
from typing import TYPE_CHECKING, overload

import numpy as np
from numpy.typing import NDArray

from mpi_lidar import __version__
from mpi_lidar.errors import MpiLidarError
from mpi_lidar.learning.features import FeatureSpec
from mpi_lidar.learning.model_card import MAX_CARD_BYTES, ModelCard, card_from_bytes, read_card
from mpi_lidar.learning.xgboost_import import import_xgboost
from mpi_lidar.locations import Location, location
from mpi_lidar.storage import objects
from mpi_lidar.storage.atomic import atomic_path

if TYPE_CHECKING:
    import dask.array as da
    import xgboost as xgb  # imported where a booster is loaded: importing XGBoost imports scikit-learn (~1 s)

MODEL_FILE = "model.ubj"
CARD_FILE = "card.json"
# Read from an object store whole, in memory: anything larger is not one of ours.
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
