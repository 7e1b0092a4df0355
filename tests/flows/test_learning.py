from __future__ import annotations

from pathlib import Path

import optuna
import pytest

from flows.evaluate import EVALUATION_ARTIFACT_KEY, TABLE2_ARTIFACT_KEY, evaluate_flow, table2_flow
from flows.train import CARD_ARTIFACT_KEY, train_flow
from flows.tune import TUNING_ARTIFACT_KEY, tune_flow
from mpi_lidar.learning import tune
from mpi_lidar.learning.features import DEFAULT_FEATURE_SET, DEFAULT_GEOMETRIC, DEFAULT_TARGET_MODE, FeatureSpec
from mpi_lidar.learning.model import load_model
from mpi_lidar.simulation.dataset import dataset_info
from tests.fast_trials import TUNE_ROWS, queue_fast_trials
from tests.flows.helpers import artifacts


@pytest.fixture(scope="module")
def tuned(small_dataset, tmp_path_factory, dask_scheduler):
    storage = f"sqlite:///{tmp_path_factory.mktemp('study') / 'optuna.db'}"
    # The study the flow makes (same settings, so the flow loads it), with one queued trial per trial to run.
    spec = FeatureSpec(dataset_info(small_dataset).frequencies_hz, DEFAULT_FEATURE_SET, DEFAULT_TARGET_MODE,
                       DEFAULT_GEOMETRIC)
    study = tune.open_study(storage, "flows", tune.TuneSettings(str(small_dataset), spec, tune_rows=TUNE_ROWS))
    queue_fast_trials(study, 3)
    state = tune_flow(data=str(small_dataset), storage=storage, study="flows", trials=3, tune_rows=TUNE_ROWS,
                      scheduler=dask_scheduler, report_dir=str(tmp_path_factory.mktemp("tuning") / "report"),
                      return_state=True)
    return storage, state


@pytest.mark.slow
def test_tune_flow__publishes_best_trial_and_plots_without_the_password(tuned):
    _, state = tuned
    result = state.result()
    assert result["trials_run"] == 3 and result["complete"] + result["pruned"] == 3
    written = {p.name for p in Path(result["report_dir"]).iterdir()}
    assert {"optimisation_history.png", "parameter_importance.png", "report.md"} <= written
    [artifact] = artifacts(str(state.state_details.flow_run_id), TUNING_ARTIFACT_KEY)
    assert "Best trial" in artifact.data and "optimisation_history.png" in artifact.data


@pytest.mark.slow
def test_train_and_evaluate_flows__model_from_the_study_and_its_report(tuned, small_dataset, tmp_path,
                                                                     dask_scheduler):
    storage, _ = tuned
    state = train_flow(data=str(small_dataset), out=str(tmp_path / "model"), study="flows", storage=storage,
                       scheduler=dask_scheduler, return_state=True)
    model = load_model(state.result()["model_dir"])
    best = optuna.load_study(study_name="flows", storage=storage).best_params
    assert {k: model.card.params[k] for k in best} == best
    [card] = artifacts(str(state.state_details.flow_run_id), CARD_ARTIFACT_KEY)
    assert "target_mode" in card.data

    evaluated = evaluate_flow(data=str(small_dataset), model=str(tmp_path / "model"), report=str(tmp_path / "r"),
                              return_state=True)
    [artifact] = artifacts(str(evaluated.state_details.flow_run_id), EVALUATION_ARTIFACT_KEY)
    assert "corrected (XGBoost)" in artifact.data and (tmp_path / "r" / "error_hist.png").exists()


@pytest.mark.slow
def test_table2_flow__table_artifact_and_files(small_dataset, small_model, tmp_path):
    state = table2_flow(data=str(small_dataset), report=str(tmp_path / "t2"), model=str(small_model), trials=1,
                        train_rows=1_500, svm_rows=500, return_state=True)
    [artifact] = artifacts(str(state.state_details.flow_run_id), TABLE2_ARTIFACT_KEY)
    assert "| XGBoost |" in artifact.data and "| SVM |" in artifact.data
    assert (tmp_path / "t2" / "table2_mae.png").exists()
