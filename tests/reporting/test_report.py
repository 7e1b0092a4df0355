"""Report pieces: tables in HTML that wrap to the page, histograms whose legend stays off the bars and titles."""

from __future__ import annotations

import numpy as np
import pytest
from matplotlib.backends.backend_agg import FigureCanvasAgg

from mpi_lidar.reporting.report import Table, error_histogram_figure

pytestmark = pytest.mark.unit


def test_table_html__in_a_box_numbers_on_one_line_long_words_breakable():
    html = Table(("scan", "MAE [mm]", "share", "notes"),
                 (("corridor_north_wing_2026-11-25_station_0001", "1,234.567", "44.4 %", "left as measured"),)).html()
    assert html.startswith('<div class="table"><table>') and html.endswith("</table></div>")
    assert html.count('<td class="number">') == 2
    assert '<td class="long">corridor_north_wing_2026-11-25_station_0001</td>' in html
    assert "<td>left as measured</td>" in html


def test_error_histogram_figure__legend_below_the_axes_not_over_the_bars():
    rng = np.random.default_rng(0)
    fig = error_histogram_figure({"raw": rng.normal(3, 2, 500), "corrected": rng.normal(0, 1, 500)}, "error [mm]")
    ax = fig.axes[0]
    assert ax.get_legend() is None and len(fig.legends) == 1
    FigureCanvasAgg(fig).draw()  # laid out as savefig lays it out
    legend, label = fig.legends[0].get_window_extent(), ax.xaxis.label.get_window_extent()
    assert legend.y1 <= label.y0 + 1  # wholly below the plotting area and its axis label
    assert [t.get_text().split(":")[0] for t in fig.legends[0].get_texts()] == ["raw", "corrected"]


def test_error_histogram_figure__no_finite_error_said_in_words_without_nan():
    fig = error_histogram_figure({"raw": np.full(4, np.nan), "corrected": np.zeros(0)}, "error [mm]")
    labels = [t.get_text() for t in fig.legends[0].get_texts()]
    assert labels == ["raw: no finite error", "corrected: no finite error"]
    assert any("no pixel with a finite error" in t.get_text() for t in fig.axes[0].texts)


def test_history_figure__legend_clear_of_the_title_and_the_points():
    import optuna

    from mpi_lidar.reporting.tuning_report import history_figure

    optuna.logging.set_verbosity(optuna.logging.WARNING)
    study = optuna.create_study(study_name="xgboost", sampler=optuna.samplers.RandomSampler(seed=0))
    study.optimize(lambda t: 0.006 + 1e-3 * t.suggest_float("learning_rate", 0.01, 0.3), n_trials=5)
    fig = history_figure(study)
    FigureCanvasAgg(fig).draw()  # laid out as savefig lays it out
    legend, label = fig.legends[0].get_window_extent(), fig.axes[0].xaxis.label.get_window_extent()
    title, axes_box = fig.axes[0].title.get_window_extent(), fig.axes[0].get_window_extent()
    assert title.y0 >= axes_box.y1 - 1 and legend.y1 <= label.y0 + 1  # title above the points, legend below
