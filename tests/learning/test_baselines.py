from __future__ import annotations

import numpy as np
import pytest

from mpi_lidar.learning.baselines import PAPER_TABLE2, Baseline, knn, table2, tune_baseline
from mpi_lidar.learning.features import weighted_depth
from mpi_lidar.reporting.table2 import table2_report
from mpi_lidar.simulation import dataset
from tests.cli_runner import call_main

pytestmark = pytest.mark.integration


@pytest.fixture(scope="module")
def result(small_dataset, small_model):
    return table2(small_dataset, small_model, train_rows=4_000, trials=2, tune_rows=1_500, svm_rows=1_000,
                  eval_rows=None)


@pytest.mark.slow
def test_table2__every_learner_beats_the_raw_depth(result):
    rows = {row.name: row for row in result.rows}
    raw = rows["raw depth 31.25MHz"]
    for name in ("KNN", "RF", "SVM", "DNN", "XGBoost"):
        assert rows[name].mae_test < 0.9 * raw.mae_test, name
        assert rows[name].train_s is not None and rows[name].train_s > 0


def test_table2__weighted_depth_row_equals_a_hand_computation(result, small_dataset):
    test = dataset.read_subsample(small_dataset, "test")
    expected = np.abs(weighted_depth(test.features, test.info.frequencies_hz) - test.target).mean()
    assert {row.name: row for row in result.rows}["weighted depth"].mae_test == pytest.approx(expected, rel=1e-12)


def test_table2__svm_fits_at_most_its_subsample(result):
    rows = {row.name: row for row in result.rows}
    assert rows["SVM"].fit_rows == 1_000 and rows["KNN"].fit_rows == 4_000


def test_tune_baseline__runs_the_requested_trials(small_dataset):
    sub = dataset.read_subsample(small_dataset, "train", max_rows=500)
    seen = []

    def counting(trial, seed):
        if trial is not None:
            seen.append(trial.number)
        return knn(trial, seed)

    params = tune_baseline(Baseline("KNN", counting, True), sub.features, sub.target, trials=3, seed=0)
    assert seen == [0, 1, 2] and set(params) == {"n_neighbors", "weights"}


def test_to_report__table_carries_the_papers_numbers(result):
    report, figures = table2_report(result)
    markdown = report.markdown()
    assert f"({PAPER_TABLE2['XGBoost'][3]:g})" in markdown and "Bayes limit" in markdown
    assert set(figures) == {"table2_mae.png"}


def test_table2_cli__writes_report_and_bad_data_is_one_line(small_dataset, tmp_path, monkeypatch, capsys):
    options = ["--report", tmp_path / "t2", "--trials", 1, "--train-rows", 500, "--svm-rows", 200]
    code, _, stderr = call_main(monkeypatch, capsys, "table2", "--data", small_dataset, *options)
    assert code == 0, stderr
    written = {p.name for p in (tmp_path / "t2").iterdir()}
    assert {"report.md", "report.html", "metrics.json", "table2_mae.png"} <= written
    code, _, stderr = call_main(monkeypatch, capsys, "table2", "--data", tmp_path / "absent.zarr", *options)
    assert code == 2 and stderr.startswith("error:") and stderr.count("\n") == 1
