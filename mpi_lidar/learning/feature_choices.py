"""The names a model's inputs and target can be chosen from, and their defaults, without importing numpy or dask.

:mod:`mpi_lidar.learning.features` builds the inputs and re-exports these; the command line reads them here,
so that ``mpi-lidar --help`` starts in well under a second.
"""

from __future__ import annotations

from typing import Literal

FeatureSet = Literal["raw", "engineered", "range_free", "physical"]
TargetMode = Literal["absolute", "residual"]
FEATURE_SETS: tuple[str, ...] = ("raw", "engineered", "range_free", "physical")
# Feature sets with no absolute depth among their inputs: they can only learn a correction (residual target).
RELATIVE_FEATURE_SETS: tuple[str, ...] = ("range_free", "physical")
# The range-free inputs plus the albedo of A, which is where range enters the physics besides the noise: over
# the working range (0.5-12 m) 1.3 % above the Bayes limit overall against 2.8 % for the engineered inputs,
# whose absolute depths a tree may split on, and 11 % for the range-free ones (800,000 train rows;
# docs/results/range-bands.md). On the paper's prior engineered features with the residual target gave 6.01 mm
# test MAE at Table I noise against 6.43 mm for the paper's raw inputs (docs/results/tradeoff.md).
DEFAULT_FEATURE_SET: FeatureSet = "physical"
DEFAULT_TARGET_MODE: TargetMode = "residual"
# Geometric inputs: better than the same prior's pixel-wise model on every rendered corner of the scene set
# (docs/results/scenes.md); such a model leaves scans without geometry uncorrected.
DEFAULT_GEOMETRIC = True
TARGET_MODES: tuple[str, ...] = ("absolute", "residual")
