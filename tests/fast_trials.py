"""Tuning trials that learn fast, queued into a study before a command or flow tunes it.

A trial stops early after tens of boosting rounds with these parameters, where the sampler's first draws (a
learning rate down to 0.01) may take up to 1,000, each reported to the study. Each set differs from the others.
"""

from __future__ import annotations

import optuna

FAST_PARAMS = (
    {"max_depth": 4, "learning_rate": 0.3, "subsample": 0.9, "colsample_bytree": 0.9, "min_child_weight": 1.0,
     "reg_lambda": 1.0},
    {"max_depth": 6, "learning_rate": 0.25, "subsample": 0.8, "colsample_bytree": 0.8, "min_child_weight": 3.0,
     "reg_lambda": 0.1},
    {"max_depth": 8, "learning_rate": 0.2, "subsample": 0.7, "colsample_bytree": 0.7, "min_child_weight": 10.0,
     "reg_lambda": 3.0},
)
TUNE_ROWS = 100  # rows a trial trains on: enough for the study, a fraction of a second per round


def queue_fast_trials(study: optuna.Study, trials: int) -> None:
    """Queue ``trials`` of :data:`FAST_PARAMS` (at most three) as the study's next trials."""
    for params in FAST_PARAMS[:trials]:
        study.enqueue_trial(params)
