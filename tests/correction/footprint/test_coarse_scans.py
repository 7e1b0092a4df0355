"""A coarse scan's footprint: where even the smallest metric blocks span more than their size and the fit settles
nowhere on them, the scene-geometry stage measures the footprint again on blocks of 2 x 2 pixels."""

from __future__ import annotations

from functools import cache

import numpy as np
import pytest

from mpi_lidar.config import Config
from mpi_lidar.correction import CorrectionOptions, analyse_geometry
from mpi_lidar.correction.footprint import FootprintEstimate, estimate_footprint
from mpi_lidar.correction.scene import (
    FINER_BLOCKS_SYSTEMATIC_SHARE,
    scene_blocks,
    settled_nowhere,
    uncertainty_footprint_m2,
)
from mpi_lidar.physics.noise import NoiseModel
from mpi_lidar.scans import geometry
from mpi_lidar.simulation.scenes import corner, render, room_with_box

pytestmark = pytest.mark.unit

ROOM_FOOTPRINT_M2 = 0.073


@cache
def coarse_room(footprint_m2: float = ROOM_FOOTPRINT_M2):
    """The corner-strength benchmark's room at half its size: 24 x 32 pixels, about 6 cm apart at 2 m."""
    return render(room_with_box(height=24, width=32, footprint_m2=footprint_m2), Config(), np.random.default_rng(0))


def usable(scan) -> np.ndarray:
    return np.where(np.isfinite(scan.depth[-1]), scan.depth[-1], np.nan).ravel().astype(np.float64)


def test_finer_block_pixels__only_where_four_pixels_span_more_than_a_block():
    room = coarse_room()
    assert geometry.finer_block_pixels(room.depth[-1], room.rays(), geometry.DEFAULT_BLOCK_M) == 2
    fine = render(corner(90.0, 2.0, 0.8, height=48, width=64), Config(), np.random.default_rng(0), coupling_gain=0.0)
    assert geometry.block_size_pixels(fine.depth[-1], fine.rays(), geometry.DEFAULT_BLOCK_M) >= 4
    assert geometry.finer_block_pixels(fine.depth[-1], fine.rays(), geometry.DEFAULT_BLOCK_M) is None


def test_analyse_geometry__a_coarse_room_measures_its_footprint_on_finer_blocks():
    scan, config = coarse_room(), Config()
    depth, options = usable(scan), CorrectionOptions()
    noise = NoiseModel.for_sensor(config.sensor, scan.frequencies_hz, options.noise_scale)
    metric = scene_blocks(scan, depth, options, noise)
    on_metric = estimate_footprint(scan, metric, np.isfinite(depth), config.sensor, noise=noise)
    assert metric.block_pixels == 4 and on_metric.pixels > 0 and not on_metric.significant, \
        "the blocks of the metric size leave the fit nothing to settle on"
    scene = analyse_geometry(scan, depth, options, config.sensor)
    assert scene.blocks.block_pixels == 2
    found = scene.footprint
    assert found.significant and 0.5 < found.area_m2 / ROOM_FOOTPRINT_M2 < 1.5
    assert scene.footprint_m2 == found.area_m2
    # The corrected depths carry the finer blocks' spread too; the significance is judged without it.
    assert found.systematic_share == FINER_BLOCKS_SYSTEMATIC_SHARE
    relative = np.hypot(np.hypot(found.sigma_m2 / found.area_m2, FINER_BLOCKS_SYSTEMATIC_SHARE),
                        0.5 * np.log(found.disagreement))
    assert found.relative_sigma == pytest.approx(relative)
    assert found.significance == pytest.approx(found.area_m2 / found.sigma_m2)


def test_analyse_geometry__a_given_footprint_works_on_a_coarse_scans_finer_blocks():
    scan = coarse_room()
    scene = analyse_geometry(scan, usable(scan), CorrectionOptions(footprint_area_m2=ROOM_FOOTPRINT_M2),
                             Config().sensor)
    assert scene.footprint is None and scene.blocks.block_pixels == 2
    assert scene.blocks.pairs.a.size > 0


def test_analyse_geometry__a_faint_coarse_room_keeps_the_finer_blocks_bound_not_the_cap():
    # At 0.001 m^2 the metric blocks' fit settles nowhere (NaN +- inf), the finer blocks' bounds the footprint
    # (about 0.002 +- 0.001 m^2, 2.3 sd; at 0.002 m^2 the estimate reads 2.9-3.1 sd, the machine's rounding
    # deciding its significance): the depths left alone carry that bound, not the 1 m^2 cap.
    scan = coarse_room(0.001)
    scene = analyse_geometry(scan, usable(scan), CorrectionOptions(), Config().sensor)
    assert scene.blocks.block_pixels == 2 and not scene.footprint.significant
    assert np.isfinite(scene.footprint.sigma_m2) and uncertainty_footprint_m2(scene.footprint) < 0.01


def test_relative_sigma__the_sd_and_the_systematic_share_in_quadrature():
    assert FootprintEstimate(0.05, 0.015, 500, 2).relative_sigma == pytest.approx(0.3)
    assert FootprintEstimate(0.05, 0.015, 500, 2, systematic_share=0.4).relative_sigma == pytest.approx(0.5)
    assert FootprintEstimate(float("nan"), float("inf"), 0, 0).relative_sigma == float("inf")


def test_relative_sigma__adds_half_the_log_distance_between_the_depths_and_the_amplitudes_measurements():
    # Depth 0.04 and amplitude 0.09 m^2 (2.25x apart): half of log 2.25 = log 1.5 joins the sd's 30 %.
    apart = FootprintEstimate(0.05, 0.015, 500, 2, depth_m2=0.04, amplitude_m2=0.09)
    assert apart.relative_sigma == pytest.approx(np.hypot(0.3, np.log(1.5)))
    assert apart.significant == FootprintEstimate(0.05, 0.015, 500, 2).significant  # judged on the sd alone
    agreeing = FootprintEstimate(0.05, 0.015, 500, 2, depth_m2=0.05, amplitude_m2=0.05)
    assert agreeing.relative_sigma == pytest.approx(0.3)


def test_settled_nowhere__only_a_fit_on_facing_surfaces_with_an_infinite_sd():
    assert settled_nowhere(FootprintEstimate(float("nan"), float("inf"), 173, 2))
    assert not settled_nowhere(FootprintEstimate(0.001, 0.002, 900, 3)), "settled, not significant: the answer"
    assert not settled_nowhere(FootprintEstimate(float("nan"), float("inf"), 0, 0)), "nothing faces: nothing to fit"
