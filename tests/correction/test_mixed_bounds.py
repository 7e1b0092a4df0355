"""A resolved pixel's two ranges carry their own 1-sigma, the two-return fit's Cramer-Rao bound: the fit's scatter
matches it, on a rendered plate before a wall it covers the resolved returns' errors about 68 % of the time, and the
other pixels' uncertainty is what it was."""

from __future__ import annotations

import numpy as np
import pytest

from benchmarks.mixed_pixels import PlateScene, render_plate
from mpi_lidar.config import Config, SensorConfig
from mpi_lidar.correction import CorrectionOptions, Flag, correct_scan
from mpi_lidar.correction._mixed_bounds import range_sigmas
from mpi_lidar.correction.baseline import frequency_offsets
from mpi_lidar.correction.estimates import ScenePart, estimate_pixels
from mpi_lidar.correction.gating import GateDecision
from mpi_lidar.correction.mixed import find_mixed
from mpi_lidar.correction.tiles import StageClock, scan_tiles
from mpi_lidar.correction.validity import check_validity
from mpi_lidar.learning.model import load_model
from mpi_lidar.physics.noise import NoiseModel
from mpi_lidar.physics.two_returns import fit_two_returns

CONFIG = Config()
ONE_SIGMA_SHARE = 0.6827  # a normal error's share within one sd
# The rendered scenes' resolved returns, both ranges each: about 170 errors, whose share within one sigma has an
# sd of 0.036 about 0.68; the tolerance is three of those sds.
COVERAGE_TOLERANCE = 0.11
DRAWS = 1000
SCENES = ((PlateScene(2.0, 0.05, 5.0, 1.0), 1), (PlateScene(2.0, 0.1, 9.0, 1.0), 2))


@pytest.mark.unit
def test_range_sigmas__match_the_scatter_of_the_closed_form_fit():
    """1,000 noisy draws of a pixel holding 70 % and 30 % of the light at 2 and 5 m: the fitted ranges' sd lie
    within 10 % of their bound (the sd of an sd from 1,000 draws is 2.2 %), the weaker's the larger."""
    freqs, c = np.asarray(CONFIG.frequencies_hz), CONFIG.sensor.speed_of_light_m_per_s
    noise = NoiseModel.for_sensor(SensorConfig(), freqs)
    w = 4 * np.pi * freqs / c
    near, far, a_near, a_far = 2.0, 5.0, 0.014, 0.006
    z = a_near * np.exp(1j * w * near) + a_far * np.exp(1j * w * far)
    sigma = noise.quadrature_sigma_v2(np.abs(z)[None, :])
    rng = np.random.default_rng(3)
    noisy = z + sigma * (rng.standard_normal((DRAWS, freqs.size)) + 1j * rng.standard_normal((DRAWS, freqs.size)))
    raw = np.concatenate([np.mod(np.angle(noisy), 2 * np.pi) / w, np.abs(noisy)], axis=1)
    fit = fit_two_returns(raw, freqs, np.broadcast_to(sigma, noisy.shape), c, np.full(DRAWS, near))
    bound = range_sigmas([near], [far], [a_near], [a_far], freqs, sigma, c)[0]
    ok = np.isfinite(fit.near_m) & (np.abs(fit.far_m - far) < 1.0)
    assert ok.mean() > 0.99
    np.testing.assert_allclose([fit.near_m[ok].std(), fit.far_m[ok].std()], bound, rtol=0.1)
    assert bound[1] > bound[0] > 0
    single = 1 / np.sqrt(((w * a_near / sigma[0]) ** 2).sum())  # one return of the nearer's light alone
    assert bound[0] > 1.5 * single, "the second return and the unknown amplitudes widen the bound"


@pytest.mark.unit
def test_range_sigmas__nan_without_a_second_return_s_light():
    freqs, c = np.asarray(CONFIG.frequencies_hz), CONFIG.sensor.speed_of_light_m_per_s
    out = range_sigmas([2.0, np.nan], [5.0, 6.0], [0.01, 0.01], [0.0, 0.01], freqs, np.full((2, 4), 1e-4), c)
    assert np.isnan(out).all()


@pytest.mark.unit
def test_correct_scan__resolved_returns_sigmas_cover_their_errors_about_68_percent(pixelwise_model):
    """Dark plates before bright walls 3 and 7 m behind, rendered with sub-ray footprints: each resolved pixel's
    corrected depth and second return, matched to the plate and the wall by range, lie within their stated 1-sigma
    (``uncertainty_m`` and ``second_returns.sigma_m``) as often as normal errors do."""
    model = load_model(pixelwise_model)
    z_scores = []
    for scene, seed in SCENES:
        scan, truth = render_plate(scene, CONFIG, np.random.default_rng(seed))
        result = correct_scan(scan, model, CorrectionOptions(), CONFIG.sensor)
        resolved = result.flags == Flag.TWO_RETURNS
        second = result.second_returns
        assert resolved.sum() > 20 and second is not None and second.sigma_m is not None
        depth, other = result.depth[resolved], second.depth_m[resolved]
        nearer_first = depth < other
        depth_truth = np.where(nearer_first, truth.plate_m[resolved], truth.wall_m[resolved])
        other_truth = np.where(nearer_first, truth.wall_m[resolved], truth.plate_m[resolved])
        z_scores += [np.abs(depth - depth_truth) / result.uncertainty_m[resolved],
                     np.abs(other - other_truth) / second.sigma_m[resolved]]
        assert np.isnan(second.sigma_m[~resolved]).all()
    stronger, weaker = np.concatenate(z_scores[::2]), np.concatenate(z_scores[1::2])
    assert stronger.size > 70 and np.isfinite(stronger).all() and np.isfinite(weaker).all()
    covered = (np.concatenate([stronger, weaker]) < 1).mean()
    assert abs(covered - ONE_SIGMA_SHARE) < COVERAGE_TOLERANCE, covered
    for each in (stronger, weaker):  # neither return's sigma is off by itself
        assert abs((each < 1).mean() - ONE_SIGMA_SHARE) < 2 * COVERAGE_TOLERANCE


@pytest.mark.unit
def test_estimate_pixels__only_the_resolved_pixels_uncertainty_comes_from_the_two_return_fit(pixelwise_model):
    """The same stages' output with the resolved pixels flagged TWO_RETURNS and with them left as valid single
    depths: every other pixel's uncertainty is bit for bit the same; the resolved ones' is the fit's bound, not the
    single depth's noise widened by its frequencies' disagreement (its Birge ratio), ten times that and more here."""
    scan, _ = render_plate(SCENES[0][0], CONFIG, np.random.default_rng(SCENES[0][1]))
    noise = NoiseModel.for_sensor(SensorConfig(), scan.frequencies_hz)
    options = CorrectionOptions()
    tiles = scan_tiles(scan, 5 * scan.shape[1])
    validity = check_validity(scan, noise, options, tiles)
    flags = np.where(validity.flags == Flag.NOT_NEEDED, np.uint8(Flag.NO_MULTIPATH), validity.flags)
    mixed = find_mixed(validity.scan, tiles, validity, GateDecision(flags.astype(np.uint8), 0, True), noise)
    resolved = mixed.decision.flags == Flag.TWO_RETURNS
    assert resolved.sum() > 20
    model = load_model(pixelwise_model)

    def uncertainty(pixel_flags):
        offsets = frequency_offsets(mixed.validity.offsets, pixel_flags, None, options)
        return estimate_pixels(mixed.validity.scan, tiles, noise, pixel_flags, mixed.validity, ScenePart(), model,
                               offsets, options, StageClock(), mixed.second_returns).uncertainty_m

    with_fit = uncertainty(mixed.decision.flags)
    as_single = uncertainty(np.where(resolved, np.uint8(Flag.NO_MULTIPATH), mixed.decision.flags).astype(np.uint8))
    assert np.array_equal(with_fit[~resolved], as_single[~resolved], equal_nan=True)
    assert np.isfinite(with_fit[resolved]).all() and np.median(with_fit[resolved] / as_single[resolved]) < 0.2
