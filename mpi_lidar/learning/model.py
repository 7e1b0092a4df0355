"""Model directories: ``model.ubj`` (XGBoost's own format, never pickle) and ``card.json``.

The card says what the model expects and how it was made: frequencies, raw and model feature names in
order, feature set and target mode, the dataset it learned from, its parameters, metrics and package
versions. Loading checks the card against the model file; correction checks it against the data.
"""

from __future__ import annotations

import hashlib
import json
from dataclasses import dataclass
from importlib.metadata import version
from pathlib import Path

import dask.array as da
import numpy as np
import xgboost as xgb
from numpy.typing import NDArray

from mpi_lidar import __version__
from mpi_lidar.errors import MpiLidarError
from mpi_lidar.learning.features import FeatureSpec
from mpi_lidar.storage.atomic import atomic_path

MODEL_SCHEMA = "mpi-lidar/model@1"
MODEL_FILE = "model.ubj"
CARD_FILE = "card.json"


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


@dataclass
class CorrectionModel:
    """A loaded, card-checked model that turns raw measurements into corrected depths."""

    booster: xgb.Booster
    card: dict[str, object]

    @property
    def spec(self) -> FeatureSpec:
        c = self.card
        return FeatureSpec(tuple(c["frequencies_hz"]), c["feature_set"], c["target_mode"],
                           bool(c.get("geometric", False)))

    def check_compatible(self, frequencies_hz: tuple[float, ...], raw_names: list[str] | tuple[str, ...],
                         source: str) -> None:
        """Refuse data whose frequencies or raw columns differ from the card's, with one clear line."""
        expected = tuple(float(f) for f in self.card["frequencies_hz"])
        if tuple(float(f) for f in frequencies_hz) != expected:
            raise MpiLidarError(
                f"{source} was measured at {_mhz(frequencies_hz)} but the model expects {_mhz(expected)}; "
                "use a model trained for these frequencies"
            )
        if list(raw_names) != list(self.card["raw_feature_names"]):
            raise MpiLidarError(f"{source} has columns {list(raw_names)} but the model expects "
                                f"{self.card['raw_feature_names']}; the data and model do not match")

    @property
    def geometric(self) -> bool:
        """Whether the model needs the geometric inputs (coupling, d_AB) of every pixel."""
        return self.spec.geometric

    def predict_depth(self, raw: NDArray, geometry: NDArray | None = None) -> NDArray[np.float64]:
        """Corrected depth [m] for raw measurements (n, 2F) in this process (XGBoost inplace_predict).

        ``geometry`` (n, 2): geometric coupling [1] and d_AB [m] per row, required by a geometric model
        (:attr:`geometric`) and ignored by the others.
        """
        spec = self.spec
        prediction = self.booster.inplace_predict(spec.transform(raw, geometry))
        return np.asarray(spec.depth(raw, prediction.astype(np.float64)))

    def predict_depth_dask(self, client: object, raw: da.Array, geometry: da.Array | None = None) -> da.Array:
        """Corrected depth [m] for a dask array of raw measurements, predicted on the cluster's workers."""
        import xgboost.dask as dxgb

        spec = self.spec
        prediction = dxgb.inplace_predict(client, self.booster, spec.transform(raw, geometry))
        return spec.depth(raw, prediction.astype(np.float64))


def _mhz(frequencies_hz: tuple[float, ...] | list[float]) -> str:
    return ", ".join(f"{f / 1e6:g}" for f in frequencies_hz) + " MHz"


def save_model(out_dir: str | Path, booster: xgb.Booster, card: dict[str, object]) -> Path:
    """Write model.ubj and card.json into a new directory, atomically (built beside it, then renamed).

    An existing directory is never overwritten: choose a new ``out_dir`` or remove the old one.
    """
    out_dir = Path(out_dir)
    with atomic_path(out_dir, what="model directory") as staging:
        staging.mkdir()
        booster.save_model(str(staging / MODEL_FILE))
        full_card = {"schema": MODEL_SCHEMA, **card, "model_sha256": file_sha256(staging / MODEL_FILE),
                     "versions": package_versions()}
        (staging / CARD_FILE).write_text(json.dumps(full_card, indent=2, sort_keys=True) + "\n")
    return out_dir


def load_model(model_dir: str | Path) -> CorrectionModel:
    """Load a model directory after checking its card: schema, file hash and feature count."""
    model_dir = Path(model_dir)
    card_path, model_path = model_dir / CARD_FILE, model_dir / MODEL_FILE
    if not card_path.is_file() or not model_path.is_file():
        raise MpiLidarError(f"{model_dir} is not a model directory (needs {MODEL_FILE} and {CARD_FILE}); "
                            "train one with 'mpi-lidar train'")
    try:
        card = json.loads(card_path.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise MpiLidarError(f"{card_path} is not valid JSON ({exc}); the model directory is damaged") from None
    if card.get("schema") != MODEL_SCHEMA:
        raise MpiLidarError(f"{card_path} has schema {card.get('schema')!r}, expected {MODEL_SCHEMA!r}")
    if card.get("model_sha256") != file_sha256(model_path):
        raise MpiLidarError(f"{model_path} does not match the hash in its card; the model directory is damaged")
    booster = xgb.Booster()
    try:
        booster.load_model(str(model_path))
    except xgb.core.XGBoostError as exc:
        raise MpiLidarError(f"{model_path} is not a readable XGBoost model: {str(exc).splitlines()[0]}") from None
    except UnicodeDecodeError:  # XGBoost echoes the file's first bytes; a pickle's are not UTF-8
        raise MpiLidarError(f"{model_path} is not a readable XGBoost model (not UBJSON; a pickle is never "
                            "loaded)") from None
    model = CorrectionModel(booster=booster, card=card)
    if booster.num_features() != len(card["feature_names"]) or card["feature_names"] != model.spec.names:
        raise MpiLidarError(f"{card_path} lists features {card['feature_names']} that do not match its model "
                            f"({booster.num_features()} inputs) or its feature set {card['feature_set']!r}")
    return model
