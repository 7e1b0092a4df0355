from __future__ import annotations

import optuna
import pytest
from optuna.trial import TrialState

from mpi_lidar.config import Config
from mpi_lidar.errors import MpiLidarError
from mpi_lidar.learning import tune
from mpi_lidar.learning.features import FeatureSpec

FREQS = Config().frequencies_hz


def settings_for(data_path, target_mode: str = "absolute", **overrides) -> tune.TuneSettings:
    options = {"tune_rows": 2_000, "num_boost_round": 40, "early_stopping_rounds": 5, **overrides}
    return tune.TuneSettings(str(data_path), FeatureSpec(FREQS, target_mode=target_mode), **options)


def assert_trials_accounted(storage_url: str, study_name: str, expected: int) -> None:
    study = optuna.load_study(study_name=study_name, storage=tune.normalise_storage_url(storage_url))
    trials = study.get_trials(deepcopy=False)
    assert len(trials) == expected, "a trial was lost or duplicated"
    assert sorted(t.number for t in trials) == list(range(expected))
    assert all(t.state in tune.FINISHED for t in trials)
    param_sets = {tuple(sorted(t.params.items())) for t in trials}
    assert len(param_sets) == expected, "two trials ran the same parameters"


@pytest.fixture(params=["sqlite", "postgresql"])
def storage_url(request, tmp_path):
    if request.param == "sqlite":
        return f"sqlite:///{tmp_path / 'optuna.db'}"
    return request.getfixturevalue("postgres_url")


@pytest.mark.slow
@pytest.mark.integration
def test_tune__parallel_trials_on_shared_storage_are_all_accounted_for(storage_url, small_dataset, cluster_client):
    # Residual target: 40 rounds reach a sane error at any learning rate TPE draws (with the absolute target,
    # six draws all below ~0.07 leave the depth centimetres off, about one run in thirty).
    report = tune.tune(cluster_client, storage_url, "parallel", settings_for(small_dataset, "residual"), trials=6)
    assert report.trials_run == 6
    assert report.complete + report.pruned == 6 and report.failed == 0
    assert 0 < report.best_value_m < 0.02
    assert set(report.best_params) == set(tune.SEARCH_SPACE)
    assert_trials_accounted(storage_url, "parallel", 6)


@pytest.mark.slow
@pytest.mark.integration
def test_tune__rerun_resumes_and_extends_without_repeating(tmp_path, small_dataset, cluster_client):
    url = f"sqlite:///{tmp_path / 'optuna.db'}"
    settings = settings_for(small_dataset, num_boost_round=10)  # trials are counted here, not judged
    first = tune.tune(cluster_client, url, "grow", settings, trials=3)
    again = tune.tune(cluster_client, url, "grow", settings, trials=3)
    extended = tune.tune(cluster_client, url, "grow", settings, trials=5)
    assert (first.trials_run, again.trials_run, extended.trials_run) == (3, 0, 2)
    assert_trials_accounted(url, "grow", 5)


@pytest.mark.slow
@pytest.mark.integration
def test_run_one_trial__failing_trial_is_recorded_and_study_goes_on(tmp_path, small_dataset, cluster_client):
    url = f"sqlite:///{tmp_path / 'optuna.db'}"
    settings = settings_for(small_dataset, num_boost_round=10)  # trials are counted here, not judged
    tune.open_study(url, "failing", settings)
    broken = settings_for(tmp_path / "missing.zarr", num_boost_round=10)
    number = tune.run_one_trial(url, "failing", broken)
    report = tune.tune(cluster_client, url, "failing", settings, trials=2)
    study = optuna.load_study(study_name="failing", storage=url)
    assert study.trials[number].state == TrialState.FAIL
    assert report.failed == 1 and report.complete + report.pruned == 2


@pytest.mark.integration
def test_open_study__same_name_with_another_search_setting_is_refused(tmp_path, small_dataset):
    url = f"sqlite:///{tmp_path / 'optuna.db'}"
    tune.open_study(url, "taken", settings_for(small_dataset))
    with pytest.raises(MpiLidarError, match="another search space"):
        tune.open_study(url, "taken", settings_for(small_dataset, tune_rows=3_000))


@pytest.mark.integration
def test_open_study__unreachable_postgres_names_host_but_never_password(small_dataset):
    url = "postgresql://analyst:s3cret-pw@127.0.0.1:1/studies"
    with pytest.raises(MpiLidarError) as error:
        tune.open_study(url, "x", settings_for(small_dataset))
    message = str(error.value)
    assert "127.0.0.1:1" in message and "analyst" in message
    assert "s3cret-pw" not in message and "\n" not in message


@pytest.mark.integration
def test_best_params__study_without_complete_trial_is_refused(tmp_path, small_dataset):
    url = f"sqlite:///{tmp_path / 'optuna.db'}"
    study = tune.open_study(url, "empty", settings_for(small_dataset))
    with pytest.raises(MpiLidarError, match="no complete trial"):
        tune.best_params(study)
    with pytest.raises(MpiLidarError, match="no study 'absent'"):
        tune.load_existing_study(url, "absent")


@pytest.mark.unit
def test_normalise_storage_url__postgres_urls_use_psycopg3():
    assert tune.normalise_storage_url("postgresql://u@h/db") == "postgresql+psycopg://u@h/db"
    assert tune.normalise_storage_url("postgres://u@h/db") == "postgresql+psycopg://u@h/db"
    assert tune.normalise_storage_url("sqlite:///x.db") == "sqlite:///x.db"

