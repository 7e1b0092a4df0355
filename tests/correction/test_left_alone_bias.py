"""The multipath a depth left alone carries in its uncertainty: partners weighed by their measured albedo, and
where the scan's footprint estimate is not significant, the footprint's root mean square under its uncertainty."""

from __future__ import annotations

from functools import cache
from pathlib import Path

import numpy as np
import pytest

from mpi_lidar.config import Config
from mpi_lidar.correction import CorrectionOptions, analyse_geometry, correct_scan
from mpi_lidar.correction.footprint import FootprintEstimate, block_albedo
from mpi_lidar.correction.options import MAX_FOOTPRINT_AREA_M2, Estimate
from mpi_lidar.correction.scene import rms_footprint_m2, uncertainty_footprint_m2
from mpi_lidar.learning.model import load_model
from mpi_lidar.simulation.scenes import corner, render

pytestmark = pytest.mark.unit


def estimate(area: float, sd: float, pixels: int = 1000) -> FootprintEstimate:
    return FootprintEstimate(area_m2=area, sigma_m2=sd, pixels=pixels, surfaces=2)


@pytest.mark.parametrize(("area", "sd", "pixels", "expected"), [
    (0.03, 0.04, 1000, 0.05),  # the root mean square of a footprint of mean 0.03 and sd 0.04
    (-0.39, 0.39, 1000, 0.39),  # a negative estimate: no footprint is negative, its spread alone
    (0.5, 2.0, 1000, MAX_FOOTPRINT_AREA_M2),  # capped as the uncalibrated pixels' upper bound
    (float("nan"), float("inf"), 1000, MAX_FOOTPRINT_AREA_M2),  # facing surfaces, a fit that settled nowhere
    (float("nan"), float("inf"), 0, 0.0),  # nothing measured: the scan says nothing of its multipath
])
def test_rms_footprint__is_the_footprints_root_mean_square_under_its_uncertainty(area, sd, pixels, expected):
    assert rms_footprint_m2(estimate(area, sd, pixels)) == pytest.approx(expected, abs=1e-12)


def test_uncertainty_footprint__is_a_significant_estimates_own():
    assert uncertainty_footprint_m2(estimate(0.04, 0.004)) == 0.04
    assert uncertainty_footprint_m2(estimate(0.004, 0.004)) == pytest.approx(np.hypot(0.004, 0.004))


@cache
def scan_of(albedo: float, seed: int):
    return render(corner(90.0, 2.0, albedo, height=32, width=64), Config(), np.random.default_rng(seed))


def usable(scan) -> np.ndarray:
    return np.where(np.isfinite(scan.depth[-1]), scan.depth[-1], np.nan).ravel().astype(np.float32)


@pytest.fixture(scope="module")
def dark_corner():
    """A corner of albedo 0.1 whose footprint estimate is not significant (-0.39 +- 0.39 m^2)."""
    scan = scan_of(0.1, 1)
    return scan, analyse_geometry(scan, usable(scan), CorrectionOptions(), Config().sensor)


def test_block_potential__weighs_each_partner_by_its_albedo(dark_corner):
    _, scene = dark_corner
    blocks = scene.blocks
    white = blocks.block_potential(0.01)
    assert white.coupling.max() < 1.0  # below the cap, the coupling is linear in the partners' albedo
    grey = blocks.block_potential(0.01, np.full(blocks.usable.size, 0.3))
    np.testing.assert_allclose(grey.coupling, 0.3 * white.coupling, rtol=1e-12)
    np.testing.assert_allclose(grey.bias_m, 0.3 * white.bias_m, rtol=1e-12, atol=1e-15)


def test_not_significant__left_alone_depths_carry_the_bias_at_the_rms_footprint(dark_corner):
    scan, scene = dark_corner
    assert scene.footprint is not None and not scene.footprint.significant and scene.footprint_m2 == 0.0
    assert not scene.bias_m.any()  # the gate's: no multipath at an unknown footprint
    albedo = np.minimum(block_albedo(scan, scene.blocks, Config().sensor), 1.0)
    expected = scene.blocks.block_potential(rms_footprint_m2(scene.footprint), albedo).bias_rows().ravel()
    left_alone = scene.left_alone_bias_m(np.arange(expected.size))
    np.testing.assert_allclose(left_alone, expected, rtol=1e-6, atol=1e-9)
    assert np.abs(left_alone).max() > 4e-3  # near the edge the unknown footprint could hold much


def test_left_alone_bias__is_below_the_white_partners_bound_on_a_dark_corner():
    scan = scan_of(0.4, 2)
    scene = analyse_geometry(scan, usable(scan), CorrectionOptions(), Config().sensor)
    assert scene.footprint is not None and scene.footprint.significant
    faced = np.flatnonzero(np.abs(scene.bias_m) > 0)
    ratio = np.abs(scene.left_alone_bias_m(faced)) / np.abs(scene.bias_m.ravel()[faced])
    # The partner blocks read an albedo near 0.4 (the scan's amplitude), and the planes weigh theirs already.
    assert np.median(ratio) == pytest.approx(0.4, abs=0.05) and ratio.max() <= 1.0 + 1e-6


@pytest.mark.parametrize(("albedo", "seed"), [(0.1, 1), (0.3, 3), (0.4, 2), (0.6, 2)])
def test_left_alone_depths__are_covered_near_their_one_sigma_share(pixelwise_model: Path, albedo, seed):
    # With white partners the corners of albedo 0.3-0.6 covered 86-89 % of these pixels. A gate at 4 mm leaves
    # enough of them alone on these small scans to tell.
    scan = scan_of(albedo, seed)
    run = correct_scan(scan, load_model(pixelwise_model), CorrectionOptions(min_multipath_bias_m=0.004))
    left = (run.estimate == Estimate.FUSED).reshape(scan.shape) & np.isfinite(scan.reference_depth)
    covered = np.abs(run.depth - scan.reference_depth)[left] <= run.uncertainty_m[left]
    assert left.sum() > 500 and 0.60 <= covered.mean() <= 0.76


def test_the_published_bias_map__stays_the_gates(pixelwise_model: Path):
    scan = scan_of(0.4, 2)
    run = correct_scan(scan, load_model(pixelwise_model))
    scene = analyse_geometry(scan, usable(scan), CorrectionOptions(), Config().sensor)
    faced = np.abs(scene.bias_m) > 0
    # The white partners' bound (the correction's own footprint estimate differs in the last digits), not the
    # albedo-weighted bias of the uncertainty, which reads about 0.4 of it here.
    assert np.median(run.multipath_bias_m[faced] / scene.bias_m[faced]) == pytest.approx(1.0, abs=0.01)
    left_alone = scene.left_alone_bias_m(np.flatnonzero(faced))
    assert np.median(left_alone / scene.bias_m[faced]) < 0.5
