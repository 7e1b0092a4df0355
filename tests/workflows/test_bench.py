from __future__ import annotations

import csv
import itertools

import numpy as np
import pytest
from click.testing import CliRunner

from mpi_lidar.cli import cli
from mpi_lidar.config import Config, PriorConfig
from mpi_lidar.correction import ConsistencyGate, CorrectionOptions
from mpi_lidar.learning.features import DEFAULT_FEATURE_SET, DEFAULT_TARGET_MODE, FeatureSpec
from mpi_lidar.physics.noise import NoiseModel
from mpi_lidar.workflows.bench import (
    TEST_STREAM,
    TRAIN_STREAM,
    BenchRow,
    gated,
    mae,
    pareto_front,
    range_guarded_depth,
    reference_xgboost,
    simulate,
    top_depth,
    with_pareto,
)

pytestmark = pytest.mark.integration

CONFIG = Config(prior=PriorConfig())  # the paper's prior: the raw error anchor and the small model's range


def _dominated_by_loops(error: list[float], cost: list[float]) -> list[bool]:
    """Independent check: a point is off the front if some other point is at least as good on both, better on one."""
    out = []
    for i in range(len(error)):
        out.append(any(error[j] <= error[i] and cost[j] <= cost[i] and (error[j] < error[i] or cost[j] < cost[i])
                       for j in range(len(error)) if j != i))
    return out


@pytest.fixture(scope="module")
def spec() -> FeatureSpec:
    return FeatureSpec(CONFIG.frequencies_hz, DEFAULT_FEATURE_SET, DEFAULT_TARGET_MODE)


@pytest.fixture(scope="module")
def small_model(spec):
    train = simulate(CONFIG, 6_000, TRAIN_STREAM)
    return reference_xgboost(spec, train).booster


def test_pareto_front__matches_a_brute_force_check_with_ties():
    rng = np.random.default_rng(3)
    for _ in range(50):
        error = rng.integers(0, 5, 12).astype(float).tolist()  # small integers: many ties
        cost = rng.integers(0, 5, 12).astype(float).tolist()
        expected = [not d for d in _dominated_by_loops(error, cost)]
        assert pareto_front(error, cost).tolist() == expected


def test_pareto_front__equal_points_are_both_on_the_front():
    assert pareto_front([1.0, 1.0, 2.0], [3.0, 3.0, 3.0]).tolist() == [True, True, False]


def test_with_pareto__throughput_higher_is_better():
    rows = [BenchRow("a", "x", 1, 1, 1.0, 100.0, 5.0, 6.0), BenchRow("b", "x", 1, 1, 2.0, 1000.0, 5.0, 6.0),
            BenchRow("c", "x", 1, 1, 3.0, 10.0, 4.0, 5.0)]
    flagged = with_pareto(rows)
    assert [r.pareto_train for r in flagged] == [True, False, True]
    assert [r.pareto_inference for r in flagged] == [False, True, True]


def test_simulate__independent_streams_and_reproducible():
    a, b = simulate(CONFIG, 2_000, TRAIN_STREAM), simulate(CONFIG, 2_000, TEST_STREAM)
    again = simulate(CONFIG, 2_000, TRAIN_STREAM)
    assert np.array_equal(a.raw, again.raw) and np.array_equal(a.target, again.target)
    assert np.intersect1d(a.target, b.target).size == 0
    low, high = CONFIG.prior.d_as_m
    assert a.target.min() >= low and a.target.max() <= high
    # raw 31.25 MHz MAE of the default prior is ~9.8 mm (docs/results/sensor.md); 2,000 rows: a few % scatter
    assert 1e3 * mae(top_depth(CONFIG.frequencies_hz)(a.raw), a.target) == pytest.approx(9.8, rel=0.12)


def test_simulate__noise_scale_and_range_override():
    quiet = simulate(CONFIG, 2_000, TEST_STREAM, noise_scale=0.0, d_as_m=(2.4, 3.0))
    assert quiet.target.min() >= 2.4 and quiet.target.max() <= 3.0
    # noiseless: the multipath bias is non-negative (the second path is longer), so depth >= truth - window error
    assert (quiet.raw[:, 3] - quiet.target).min() > -1e-3


def test_mae__is_error_metrics_mae_and_nan_when_an_estimate_is_not_finite():
    truth = np.array([1.0, 2.0, 3.0])
    assert mae(np.array([1.5, 2.0, 2.0]), truth) == pytest.approx(0.5)
    assert np.isnan(mae(np.array([1.5, np.nan, 2.0]), truth))


def test_reference_xgboost__the_projects_training_with_its_defaults(spec):
    from mpi_lidar.learning.train import DEFAULT_EARLY_STOPPING, train_arrays

    train = simulate(CONFIG, 1_500, TRAIN_STREAM)
    ours = reference_xgboost(spec, train)
    again = train_arrays(spec.transform(train.raw), spec.target(train.raw, train.target))
    assert ours.booster.num_boosted_rounds() == again.booster.num_boosted_rounds() == ours.best_iteration + 1
    assert ours.validation_rows == 150 and ours.best_iteration + DEFAULT_EARLY_STOPPING < 2_000
    np.testing.assert_array_equal(ours.booster.inplace_predict(spec.transform(train.raw)),
                                  again.booster.inplace_predict(spec.transform(train.raw)))


def test_range_guarded_depth__raw_outside_the_prior_range_model_inside(small_model, spec):
    far = simulate(CONFIG, 3_000, TEST_STREAM + 1, d_as_m=(1.0, 3.0))
    raw_depth = top_depth(CONFIG.frequencies_hz)(far.raw)
    tol = 0.01
    guarded = range_guarded_depth(small_model, spec, far.raw, CONFIG.prior.d_as_m, tolerance_m=tol)
    nearest = 1.4 * (1 - CorrectionOptions().near_range_fraction)  # measured nearer is truly nearer
    outside = (raw_depth < nearest - tol) | (raw_depth > 2.4 + tol)
    assert outside.sum() > 1_000 and (~outside).sum() > 1_000
    assert np.array_equal(guarded[outside], raw_depth[outside])
    model = np.asarray(spec.depth(far.raw, small_model.inplace_predict(spec.transform(far.raw)).astype(np.float64)))
    np.testing.assert_allclose(guarded[~outside], model[~outside], rtol=0, atol=1e-9)


def test_range_guarded_depth__not_worse_than_raw_beyond_the_range(small_model, spec):
    far = simulate(CONFIG, 5_000, TEST_STREAM + 1, d_as_m=(2.4, 3.0))
    raw_mae = mae(top_depth(CONFIG.frequencies_hz)(far.raw), far.target)
    guarded_mae = mae(range_guarded_depth(small_model, spec, far.raw, CONFIG.prior.d_as_m), far.target)
    # the default guard (no tolerance) corrects only rows whose measured depth is inside the trained range
    assert guarded_mae <= raw_mae * 1.002


def test_gated__skipped_rows_keep_the_raw_depth():
    test = simulate(CONFIG, 3_000, TEST_STREAM)
    predict = gated(lambda raw: np.full(raw.shape[0], -1.0), CONFIG)
    depth = predict(test.raw)
    noise = NoiseModel.for_sensor(CONFIG.sensor, CONFIG.frequencies_hz)
    needs = ConsistencyGate(0.01).needs_correction(test.raw, noise)
    assert 0 < needs.sum() < needs.size
    assert (depth[needs] == -1.0).all()
    assert np.array_equal(depth[~needs], test.raw[~needs, 3].astype(np.float64))


@pytest.mark.slow
def test_bench__quick_command_writes_tables_plots_and_pareto_flags(tmp_path):
    out = tmp_path / "bench"
    result = CliRunner().invoke(cli, ["bench", "--out", str(out), "--quick", "--rows", "600"])
    assert result.exit_code == 0, result.output
    for name in ("report.md", "report.html", "metrics.json", "tradeoff.png", "learning_curve.png", "noise.png",
                 "tradeoff.csv", "learning_curve.csv", "noise.csv", "out_of_range.csv"):
        assert (out / name).is_file(), name
    with (out / "tradeoff.csv").open() as handle:
        rows = list(csv.DictReader(handle))
    assert list(rows[0]) == ["method", "family", "fit_rows", "test_rows", "train_s", "rows_per_s", "mae_mm",
                             "rmse_mm", "pareto_train", "pareto_inference"]
    names = [r["method"] for r in rows]
    for expected in ("raw depth 31.25 MHz", "weighted depth", "Prony two-path", "KNN (k=10, distance)",
                     "XGBoost 30x4", "XGBoost 30x4 + gate"):
        assert expected in names
    error = [float(r["mae_mm"]) for r in rows]
    for flag, cost in (("pareto_train", [float(r["train_s"]) for r in rows]),
                       ("pareto_inference", [-float(r["rows_per_s"]) for r in rows])):
        expected = [not d for d in _dominated_by_loops(error, cost)]
        assert [r[flag] == "True" for r in rows] == expected
    assert any(r["pareto_train"] == "True" for r in rows)
    raw = next(r for r in rows if r["method"] == "raw depth 31.25 MHz")
    assert float(raw["train_s"]) == 0.0 and 5.0 < float(raw["mae_mm"]) < 15.0
    assert all(np.isfinite(float(v)) for r in rows for k, v in r.items() if k.endswith("_mm"))
    with (out / "learning_curve.csv").open() as handle:
        assert [int(r["train_rows"]) for r in csv.DictReader(handle)] == [150, 600]
    assert "| method |" in (out / "report.md").read_text()


def test_bench__rejects_too_few_rows(tmp_path):
    result = CliRunner().invoke(cli, ["bench", "--out", str(tmp_path / "b"), "--rows", "5"])
    assert result.exit_code != 0 and "5" in result.output


@pytest.mark.parametrize(("a", "b"), list(itertools.combinations(range(3), 2)))
def test_pareto_front__a_strictly_better_point_removes_the_other(a, b):
    error, cost = [3.0, 3.0, 3.0], [3.0, 3.0, 3.0]
    error[a] = 1.0
    front = pareto_front(error, cost)
    assert front[a] and not front[b]
