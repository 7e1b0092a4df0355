"""The prior-coverage benchmark's measurement: the gated pixels' geometric inputs of corners, against the corners'
own geometry and against the priors they should or should not fit in."""

from __future__ import annotations

import math

import numpy as np
import pytest

from benchmarks.prior_coverage import BOARD_M, HALF_HEIGHT_M, GatedInputs, gated_inputs, reach_of, scaled_corner
from mpi_lidar.config import Config, preset
from mpi_lidar.simulation.scenes import render


def _gated(angle_deg: float):
    config = Config()
    return gated_inputs(render(scaled_corner(angle_deg, 2.0, 4), config, np.random.default_rng(7)), config)


@pytest.fixture(scope="module")
def corners():
    return {angle: _gated(angle) for angle in (60.0, 90.0, 120.0)}


@pytest.mark.integration
def test_gated_inputs__no_partner_farther_than_the_boards_allow(corners):
    for angle, found in corners.items():
        assert found.values.shape[0] > 50, angle
        # Two points on boards of length BOARD_M meeting at angle_deg, at most 2 * HALF_HEIGHT_M apart in height.
        chord_m = 2 * BOARD_M * math.sin(math.radians(angle) / 2)
        assert found.d_ab_m.min() > 0 and found.d_ab_m.max() <= math.hypot(chord_m, 2 * HALF_HEIGHT_M), angle
        assert (found.rho_aba > 0).all() and (found.values[:, 2] > 0).all(), angle


@pytest.mark.integration
def test_gated_inputs__narrower_corners_reach_further_past_the_papers_prior(corners):
    wide, paper = reach_of(preset("wide").prior), reach_of(Config().prior)
    medians = [float(np.median(corners[angle].d_ab_m)) for angle in (60.0, 90.0, 120.0)]
    assert medians[0] > medians[1] > medians[2]
    inside_paper = [corners[angle].inside(paper) for angle in (60.0, 90.0, 120.0)]
    assert inside_paper[0] < inside_paper[1] < inside_paper[2]
    assert all(corners[angle].inside(wide) >= 0.99 for angle in corners)


@pytest.mark.unit
def test_gated_inputs__share_inside_counts_both_limits():
    found = GatedInputs(np.array([[0.5, 0.1, 0.2], [1.5, 0.1, 0.2], [0.5, 0.3, 0.2], [0.9, 0.2, 0.2]]))
    assert found.inside((1.0, 0.2)) == 0.5 and math.isnan(GatedInputs(np.zeros((0, 3))).inside((1.0, 0.2)))
