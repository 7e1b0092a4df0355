"""Run time against error: every depth estimator on the same simulated train and test rows.

Data are simulated in this process with the project's prior and sensor model (no store): the train rows
and the test rows come from independent seed streams, so the test set is a fresh draw from the prior and
never a near-duplicate of a training row. Each method is timed twice: its training (fit) wall time and its
inference throughput (rows per second, one process). The Pareto front marks the methods that no other
method beats on both error and time.

The parts, each private: ``_sample`` (the simulated rows), ``_methods`` (the estimators), ``_measure`` (timing
and scoring one estimator), ``_curves`` (the accuracy curves and the out-of-range rows), ``_run`` (the whole
benchmark) and ``_report`` (its tables, figures and files).
"""

from __future__ import annotations

from mpi_lidar.workflows.bench._curves import (
    CurvePoint,
    OutOfRange,
    curve_point,
    range_guarded_depth,
    reference_xgboost,
)
from mpi_lidar.workflows.bench._measure import BenchRow, measure, pareto_front, score, with_pareto
from mpi_lidar.workflows.bench._methods import Method, Predictor, gated, methods, top_depth, xgboost_method
from mpi_lidar.workflows.bench._report import (
    curve_figure,
    curve_table,
    out_of_range_table,
    tradeoff_figure,
    tradeoff_table,
    write_bench,
)
from mpi_lidar.workflows.bench._run import NOISE_SCALES, XGB_SIZES, BenchPlan, BenchResult, run_bench
from mpi_lidar.workflows.bench._sample import TEST_STREAM, TRAIN_STREAM, Sample, mae, simulate

__all__ = [
    "NOISE_SCALES", "TEST_STREAM", "TRAIN_STREAM", "XGB_SIZES", "BenchPlan", "BenchResult", "BenchRow",
    "CurvePoint", "Method", "OutOfRange", "Predictor", "Sample", "curve_figure", "curve_point", "curve_table",
    "gated", "mae", "measure", "methods", "out_of_range_table", "pareto_front", "range_guarded_depth",
    "reference_xgboost", "run_bench", "score", "simulate", "top_depth", "tradeoff_figure", "tradeoff_table",
    "with_pareto", "write_bench", "xgboost_method",
]
