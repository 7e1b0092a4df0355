"""Report of a tuning study: the best trial, every trial, the optimisation history and parameter importances."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import optuna
from matplotlib.figure import Figure
from optuna.trial import TrialState

from mpi_lidar.reporting.report import Report, Table, legend_below


def history_figure(study: optuna.Study) -> Figure:
    """Validation MAE of each complete trial and the best so far (the optimisation history)."""
    complete = study.get_trials(deepcopy=False, states=(TrialState.COMPLETE,))
    numbers = np.array([t.number for t in complete])
    values = 1e3 * np.array([t.value for t in complete])
    fig = Figure(figsize=(6.4, 4.2), layout="constrained")
    ax = fig.subplots()
    ax.scatter(numbers, values, s=14, label="trial")
    if values.size:
        ax.step(numbers, np.minimum.accumulate(values), where="post", color="#c0392b", label="best so far")
    ax.set_xlabel("trial (number)")
    ax.set_ylabel("validation MAE [mm]")
    ax.set_title(f"Optimisation history of {study.study_name}")
    legend_below(fig)
    return fig


def importance_figure(study: optuna.Study) -> Figure | None:
    """fANOVA importance of each parameter; None with fewer than two complete trials (nothing to compare)."""
    if len(study.get_trials(deepcopy=False, states=(TrialState.COMPLETE,))) < 2:
        return None
    importances = optuna.importance.get_param_importances(study)
    fig = Figure(figsize=(6.4, 4.0), layout="constrained")
    ax = fig.subplots()
    names = list(importances)[::-1]
    ax.barh(names, [importances[n] for n in names], color="#3b6ea5")
    ax.set_xlabel("importance, fANOVA [share of variance]")
    ax.set_title("Hyperparameter importance")
    return fig


def tuning_report(study: optuna.Study, storage_label: str) -> tuple[Report, dict[str, Figure]]:
    """Best trial and trial table (values in mm) with the history and importance plots."""
    figures = {"optimisation_history.png": history_figure(study)}
    importance = importance_figure(study)
    notes = []
    if importance is None:
        notes.append("Parameter importance needs at least two complete trials.")
    else:
        figures["parameter_importance.png"] = importance
    trials = Table(("trial", "state", "validation MAE [mm]", "seconds"), tuple(
        (str(t.number), t.state.name.lower(), f"{1e3 * t.value:.3f}" if t.value is not None else "",
         f"{t.duration.total_seconds():.1f}" if t.duration else "")
        for t in study.get_trials(deepcopy=False)))
    complete = study.get_trials(deepcopy=False, states=(TrialState.COMPLETE,))
    best = (f"Best trial {study.best_trial.number}: validation MAE {1e3 * study.best_value:.3f} mm with "
            f"{study.best_params}." if complete else "No complete trial yet.")
    report = Report(title=f"Tuning study {study.study_name}",
                    blocks=[f"Storage {storage_label}.", best, trials, *notes, *(Path(name) for name in figures)],
                    data={"study": study.study_name, "best_params": study.best_params if complete else {},
                          "best_value_m": study.best_value if complete else None})
    return report, figures
