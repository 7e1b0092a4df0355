"""Hyperparameter tuning with Optuna's TPE sampler on a shared RDB storage, trials run as Dask tasks.

The study lives in the storage (SQLite file by default, PostgreSQL for clusters). It is created once,
on the client, before any worker starts; every trial is then a Dask task that loads the study, asks the
shared TPE sampler for parameters, trains XGBoost on a subsample of the train split with early stopping
and pruning, and tells the result. A failing trial is recorded as failed and the study goes on; a trial
whose worker died is marked failed by the storage heartbeat. ``trials`` is the number of finished
(complete or pruned) trials the study should hold, so running again resumes or extends it.
"""

from __future__ import annotations

import hashlib
import json
import os
import time
import warnings
from collections.abc import Callable
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path

import numpy as np
import optuna
import sqlalchemy.exc
import xgboost as xgb
from distributed import Client, Future, as_completed
from optuna.trial import TrialState
from optuna_integration import XGBoostPruningCallback
from sqlalchemy.engine import make_url

from mpi_lidar.errors import MpiLidarError
from mpi_lidar.learning.features import FeatureSpec
from mpi_lidar.learning.train import check_dataset_matches, training_geometry, xgb_params
from mpi_lidar.locations import driver_url, location
from mpi_lidar.redact import MASK, SECRET_KEYS, redact
from mpi_lidar.simulation import dataset

DEFAULT_TRIALS = 30
DEFAULT_TUNE_ROWS = 100_000
HEARTBEAT_S = 10
MAX_REPLACED_TASKS = 10
FINISHED = (TrialState.COMPLETE, TrialState.PRUNED)
STORAGE_URL_VARIABLE = "MPI_LIDAR_STORAGE_URL"

# (low, high, log) per parameter; max_depth is an integer.
SEARCH_SPACE: dict[str, tuple[float, float, bool]] = {
    "max_depth": (3, 12, False),
    "learning_rate": (0.01, 0.3, True),
    "subsample": (0.5, 1.0, False),
    "colsample_bytree": (0.5, 1.0, False),
    "min_child_weight": (0.1, 50.0, True),
    "reg_lambda": (1e-3, 10.0, True),
}


@dataclass(frozen=True)
class TuneSettings:
    """What every trial of a study shares; its signature guards a study name against reuse."""

    data_path: str
    spec: FeatureSpec
    tune_rows: int = DEFAULT_TUNE_ROWS
    num_boost_round: int = 1000
    early_stopping_rounds: int = 30
    subsample_seed: int = 0

    def signature(self, config_sha256: str) -> str:
        payload = {
            "search_space": SEARCH_SPACE, "dataset_config_sha256": config_sha256,
            "feature_set": self.spec.feature_set, "target_mode": self.spec.target_mode,
            "tune_rows": self.tune_rows, "num_boost_round": self.num_boost_round,
        }
        if self.spec.geometric:  # absent when False, so the signatures of existing studies do not change
            payload["geometric"] = True
        return hashlib.sha256(json.dumps(payload, sort_keys=True).encode()).hexdigest()


def normalise_storage_url(url: str) -> str:
    """Let users write postgresql:// and get the psycopg 3 driver this project installs."""
    for prefix in ("postgresql://", "postgres://"):
        if url.startswith(prefix):
            return "postgresql+psycopg://" + url[len(prefix):]
    return url


def masked(url: str) -> str:
    """The storage URL with any password replaced by ***, for messages and logs."""
    try:
        return redact(make_url(url).render_as_string(hide_password=True))
    except (sqlalchemy.exc.ArgumentError, ValueError):  # ValueError: a port that is not a number
        return "<unparseable storage URL>"  # not a URL: no telling which part of it is a secret


def _storage(url: str) -> optuna.storages.RDBStorage:
    url = driver_url(normalise_storage_url(url))  # a password's unencoded '@' is no host
    # Every study is opened here: optuna's one line per trial is noise at archive scale. Set where a study is
    # opened, not on import: importing this module changes no logging of the caller's.
    optuna.logging.set_verbosity(optuna.logging.WARNING)
    # The heartbeat that fails the trials of dead workers is marked experimental; it is what we rely on.
    warnings.filterwarnings("ignore", category=optuna.exceptions.ExperimentalWarning)
    try:
        return optuna.storages.RDBStorage(url, heartbeat_interval=HEARTBEAT_S, engine_kwargs={"pool_pre_ping": True})
    except (sqlalchemy.exc.DBAPIError, sqlalchemy.exc.ArgumentError, ImportError, ValueError) as exc:
        reason = str(getattr(exc, "orig", exc)).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
        raise MpiLidarError(f"cannot reach Optuna storage {masked(url)}: {_strip_password(reason, url)}; check "
                            "the host, port and database, and that the server runs") from None


def _strip_password(text: str, url: str) -> str:
    try:
        parsed = make_url(url)
    except (sqlalchemy.exc.ArgumentError, ValueError):
        return redact(text)
    secrets = [parsed.password, *(v for k, v in parsed.query.items() if k.lower() in SECRET_KEYS)]
    for secret in secrets:
        for value in ([secret] if isinstance(secret, str) else list(secret or ())):
            text = text.replace(value, MASK) if value else text
    return redact(text)


MAX_STUDY_NAME = 512  # Optuna's column width for study names


def check_study_name(name: str) -> str:
    """A study name every storage accepts: 1 to 512 printable characters."""
    if not name or len(name) > MAX_STUDY_NAME or not name.isprintable():
        raise MpiLidarError(f"study name {name[:40]!r}{'...' if len(name) > 40 else ''} must be 1 to "
                            f"{MAX_STUDY_NAME} printable characters; choose another --study")
    return name


def open_study(storage_url: str, study_name: str, settings: TuneSettings) -> optuna.Study:
    """Create the study (or load it) and check that it was made for the same search space and data."""
    check_study_name(study_name)
    info = dataset.dataset_info(settings.data_path)
    check_dataset_matches(settings.spec, info)
    study = optuna.create_study(
        storage=_storage(storage_url), study_name=study_name, direction="minimize",
        sampler=optuna.samplers.TPESampler(constant_liar=True), load_if_exists=True,
    )
    signature = settings.signature(info.config_sha256)
    found = study.user_attrs.get("signature")
    if found is None:
        study.set_user_attr("signature", signature)
        study.set_user_attr("settings", {"search_space": SEARCH_SPACE, "feature_set": settings.spec.feature_set,
                                         "target_mode": settings.spec.target_mode, "tune_rows": settings.tune_rows,
                                         "geometric": settings.spec.geometric,
                                         "dataset_config_sha256": info.config_sha256})
    elif found != signature:
        raise MpiLidarError(f"study {study_name!r} in {masked(storage_url)} was made for another search space, "
                            "dataset or feature set; choose a new --study name")
    return study


def suggest_params(trial: optuna.Trial) -> dict[str, object]:
    params: dict[str, object] = {}
    for name, (low, high, log) in SEARCH_SPACE.items():
        if name == "max_depth":
            params[name] = trial.suggest_int(name, int(low), int(high))
        else:
            params[name] = trial.suggest_float(name, low, high, log=log)
    return params


@lru_cache(maxsize=2)
def _tuning_data(data_path: str, spec: FeatureSpec, rows: int, seed: int) -> tuple[xgb.DMatrix, xgb.DMatrix]:
    """A seeded subsample of the train split, four fifths to fit and one fifth to validate (per process)."""
    sub = dataset.read_subsample(data_path, split="train", max_rows=rows, seed=seed)
    x, y = spec.transform(sub.features, training_geometry(spec, sub)), spec.target(sub.features, sub.target)
    holdout = np.arange(x.shape[0]) % 5 == 0
    # One thread, like the trial itself: a worker is one core, and parallelism comes from parallel trials.
    fit = xgb.QuantileDMatrix(x[~holdout], y[~holdout], nthread=1)
    return fit, xgb.DMatrix(x[holdout], y[holdout], nthread=1)


def objective(trial: optuna.Trial, settings: TuneSettings) -> float:
    """Validation MAE [m] of XGBoost with the trial's parameters, early-stopped and pruned."""
    dfit, dval = _tuning_data(settings.data_path, settings.spec, settings.tune_rows, settings.subsample_seed)
    params = xgb_params(suggest_params(trial), nthread=1, verbosity=0)
    evals_result: dict[str, dict[str, list[float]]] = {}
    booster = xgb.train(
        params, dfit, num_boost_round=settings.num_boost_round, evals=[(dval, "validation")],
        early_stopping_rounds=settings.early_stopping_rounds, evals_result=evals_result, verbose_eval=False,
        callbacks=[XGBoostPruningCallback(trial, "validation-mae")],
    )
    trial.set_user_attr("best_iteration", int(booster.best_iteration))
    return float(min(evals_result["validation"]["mae"]))


def run_one_trial(storage_url: str, study_name: str, settings: TuneSettings) -> int:
    """Load the study from the shared storage and run one trial there (a Dask task). Returns its number."""
    optuna.logging.set_verbosity(optuna.logging.WARNING)
    study = optuna.load_study(study_name=study_name, storage=_storage(storage_url),
                              sampler=optuna.samplers.TPESampler(constant_liar=True))
    numbers: list[int] = []
    study.optimize(lambda trial: objective(trial, settings), n_trials=1, catch=(Exception,),
                   callbacks=[lambda _study, trial: numbers.append(trial.number)])
    return numbers[0]


@dataclass(frozen=True)
class TuneReport:
    study_name: str
    trials_run: int
    complete: int
    pruned: int
    failed: int
    best_value_m: float | None
    best_params: dict[str, object]
    wall_s: float


def count(study: optuna.Study, *states: TrialState) -> int:
    return len(study.get_trials(deepcopy=False, states=states))


def tune(
    client: Client, storage_url: str, study_name: str, settings: TuneSettings, trials: int = DEFAULT_TRIALS,
    on_trial: Callable[[int], None] | None = None,
) -> TuneReport:
    """Run trials on the cluster until the study holds ``trials`` finished ones.

    When the tasks are done and the study still holds fewer finished trials than asked for (a trial task
    raised because its storage connection was cut by a database restart or failover, or a trial failed),
    new trial tasks make up the difference, up to ``MAX_REPLACED_TASKS`` in all; an interrupted trial is
    failed by the storage heartbeat. ``trials_run`` of the report counts the trial tasks that returned.
    """
    started = time.perf_counter()
    study = open_study(storage_url, study_name, settings)
    todo = max(0, trials - count(study, *FINISHED))

    def submit() -> Future:
        return client.submit(run_one_trial, storage_url, study_name, settings, pure=False)

    running = as_completed([submit() for _ in range(todo)])
    ran = replaced = 0
    error: Exception | None = None
    while True:
        for future in running:
            try:
                number = future.result()
            except Exception as exc:  # the trial's own errors are caught in run_one_trial: this is infrastructure
                error = exc
                continue
            ran += 1
            if on_trial is not None:
                on_trial(number)
        missing = trials - count(study, *FINISHED)
        if missing <= 0 or replaced >= MAX_REPLACED_TASKS:
            break
        missing = min(missing, MAX_REPLACED_TASKS - replaced)
        replaced += missing
        running = as_completed([submit() for _ in range(missing)])
    if error is not None and count(study, *FINISHED) < trials:
        reason = _strip_password((str(error).splitlines() or [""])[0], storage_url)
        raise MpiLidarError(f"study {study_name!r} stopped short of {trials} finished trials after {replaced} "
                            f"replaced trial tasks; the last failed with {type(error).__name__}: {reason}")
    return tune_report(study, ran, time.perf_counter() - started)


def tune_report(study: optuna.Study, trials_run: int, wall_s: float) -> TuneReport:
    complete = count(study, TrialState.COMPLETE)
    best = study.best_trial if complete else None
    return TuneReport(
        study_name=study.study_name, trials_run=trials_run, complete=complete,
        pruned=count(study, TrialState.PRUNED), failed=count(study, TrialState.FAIL),
        best_value_m=best.value if best else None,
        best_params=dict(best.params) if best else {}, wall_s=wall_s,
    )


def load_existing_study(storage_url: str, study_name: str) -> optuna.Study:
    check_study_name(study_name)
    try:
        return optuna.load_study(study_name=study_name, storage=_storage(storage_url))
    except KeyError:
        raise MpiLidarError(f"no study {study_name!r} in {masked(storage_url)}; run 'mpi-lidar tune' first") from None


def best_params(study: optuna.Study) -> dict[str, object]:
    """The best complete trial's parameters, to feed the final training."""
    if not count(study, TrialState.COMPLETE):
        raise MpiLidarError(f"study {study.study_name!r} has no complete trial yet; run 'mpi-lidar tune' first")
    return dict(study.best_trial.params)


def storage_url(url: str | None, data_path: str | Path) -> str:
    """The study storage: ``url``, else ``$MPI_LIDAR_STORAGE_URL``, else the SQLite file beside the dataset.

    The environment variable keeps a password out of command lines, flow parameters and shell history;
    PostgreSQL also takes the password from ``PGPASSWORD`` or ``~/.pgpass`` when the URL has none.
    """
    return url or os.environ.get(STORAGE_URL_VARIABLE) or default_storage(data_path)


def default_storage(data_path: str | Path) -> str:
    """SQLite file beside the dataset: the embedded default. A dataset in an object store has no folder to put
    it in, and the Dask workers that run the trials (on machines without a shared disk) could not all reach a
    file on this one: refused, asking for a storage URL."""
    where = location(data_path)
    if not where.is_local:
        raise MpiLidarError(f"the dataset {where} is in an object store, so the Optuna study cannot be kept in a "
                            f"SQLite file beside it; give its storage with --storage or ${STORAGE_URL_VARIABLE} "
                            "(postgresql://user@db-host/optuna, which every worker reaches)")
    return f"sqlite:///{where.local_path().resolve().parent / 'optuna.db'}"
