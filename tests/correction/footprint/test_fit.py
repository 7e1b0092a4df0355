"""The footprint fit (mpi_lidar.correction.footprint._fit) on a corner seen as two strips: its statistical sd, a
surface that fixes no plane, and the amplitude's estimate joined with the depth's."""

from __future__ import annotations

import numpy as np
import pytest

from mpi_lidar.config import Config
from mpi_lidar.correction.footprint import EstimateMethod, _fit
from mpi_lidar.correction.footprint._fit import FootprintFit


def strip_corner_problem(depth: np.ndarray | None, true_m2: float, noise_m: float) -> FootprintFit:
    """The fit of a 90-degree corner 2 m away seen as two strips 10 cm high and 2-30 cm from the edge, each
    pixel's coupling kappa = 0.13 / (pi^2 a^2) at the distance a from the edge; ``depth`` None: noiseless
    at ``true_m2``."""
    freqs = np.array(Config().frequencies_hz)
    metres_per_rad = Config().sensor.speed_of_light_m_per_s / (4 * np.pi * freqs)
    along_edge, up = np.meshgrid(np.linspace(0.02, 0.3, 40), np.linspace(-0.05, 0.05, 5), indexing="ij")
    a = np.tile(along_edge.ravel(), 2)
    side = np.repeat([-1.0, 1.0], along_edge.size)
    points = np.column_stack([side * a * np.sqrt(0.5), np.tile(up.ravel(), 2), 2.0 - a * np.sqrt(0.5)])
    true_range = np.linalg.norm(points, axis=1)
    kappa = 0.13 / (np.pi**2 * a**2)
    phasor = 0.5 * kappa[:, None] * np.exp(1j * a[:, None] * np.sqrt(2) / metres_per_rad[None])
    sigma = np.full((a.size, freqs.size), noise_m)
    arguments = (sigma, phasor, kappa, metres_per_rad, np.ones_like(sigma), points / true_range[:, None], side, None)
    if depth is None:
        depth = true_range[:, None] + FootprintFit(np.zeros_like(sigma), *arguments).bias(true_m2)[0]
    return FootprintFit(depth, *arguments)


@pytest.mark.unit
def test_estimate__statistical_sigma_matches_the_scatter_over_noise_draws(monkeypatch):
    # Each strip's plane rests on its far pixels (the anchors) and reaches the edge by extrapolation, so the
    # anchors' noise moves the estimate more than the fit rows' own noise: sigma must hold both (Monte Carlo).
    monkeypatch.setattr(_fit, "DEPTH_SYSTEMATIC_SHARE", 0.0)
    rng = np.random.default_rng(0)
    clean = strip_corner_problem(None, 0.02, 0.002).depth
    found = [strip_corner_problem(clean + rng.normal(0.0, 0.002, clean.shape), 0.02, 0.002)
             .solve(EstimateMethod.PLANES, with_amplitude=False, start_m2=0.02) for _ in range(300)]
    estimates = np.array([f.area_m2 for f in found])
    assert np.median([f.sigma_m2 for f in found]) == pytest.approx(estimates.std(), rel=0.2)
    assert estimates.mean() == pytest.approx(0.02, rel=0.1)


@pytest.mark.unit
def test_estimate__a_surface_whose_anchors_lie_along_a_line_is_left_out():
    # One row of pixels fixes no plane: it could turn about the row and put any bias on the surface's other
    # pixels (on a rendered 60-degree corner such a strip made sigma 2 m^2). The row's 60 anchors are 40 % of
    # its 150 pixels, so the corner keeps its own anchors.
    clean = strip_corner_problem(None, 0.02, 0.002)
    alone = strip_corner_problem(clean.depth + np.random.default_rng(1).normal(0.0, 0.002, clean.depth.shape),
                                 0.02, 0.002)
    row = np.column_stack([np.linspace(-0.3, 0.3, 150), np.full(150, 0.12), np.full(150, 2.2)])
    row_kappa = np.where(np.arange(150) < 60, 1e-4, 5.0)
    row_phasor = 0.5 * row_kappa[:, None] * np.exp(0.1j * np.arange(1, 5))[None]
    both = FootprintFit(
        np.concatenate([alone.depth, np.linalg.norm(row, axis=1)[:, None] + np.zeros((1, 4))]),
        np.concatenate([alone.sigma, np.full((150, 4), 0.002)]), np.concatenate([alone.phasor, row_phasor]),
        np.concatenate([alone.coupling, row_kappa]), alone.metres_per_rad, np.ones((alone.depth.shape[0] + 150, 4)),
        np.concatenate([alone.rays, row / np.linalg.norm(row, axis=1, keepdims=True)]),
        np.concatenate([alone.surface, np.full(150, 2)]), None)
    expected, found = (p.solve(EstimateMethod.PLANES, with_amplitude=False, start_m2=0.02) for p in (alone, both))
    assert found.surfaces == 2
    assert found.area_m2 == pytest.approx(expected.area_m2, rel=1e-6)
    assert found.sigma_m2 == pytest.approx(expected.sigma_m2, rel=1e-6)


def lit_strip_corner(true_m2: float, light_m2: float, noise_m: float, seed: int) -> FootprintFit:
    """:func:`strip_corner_problem` with noisy depth at ``true_m2`` and a Lambertian amplitude (albedo 0.6)
    that holds the multipath gain of ``light_m2``, with the noise the depth's implies (sigma_log =
    sigma_depth / metres per radian)."""
    rng = np.random.default_rng(seed)
    clean = strip_corner_problem(None, true_m2, noise_m)
    ranges = 1.0 / np.einsum("ni,ni->n", clean.rays, np.where(clean.surface[:, None] == 0, [-0.5, 0, 0.5],
                                                                 [0.5, 0, 0.5]))
    direct = 0.6 / (np.sqrt(0.5) * ranges**3)  # rho cos_i / t^2, cos_i = 1 / (t |u|) with |u| = sqrt(1/2)
    gain = clean.bias(light_m2)[2]
    amplitude = direct[:, None] * gain * np.exp(rng.normal(0.0, 1.0, gain.shape) * clean.sigma_log)
    return FootprintFit(clean.depth + rng.normal(0.0, noise_m, clean.depth.shape), clean.sigma,
                                clean.phasor, clean.coupling, clean.metres_per_rad, amplitude, clean.rays,
                                np.where(clean.surface == 0, -1.0, 1.0), None)


@pytest.mark.unit
def test_estimate__the_amplitude_joins_the_depth_by_their_relative_uncertainties():
    # Depth and light both hold 0.02 m^2 and Gaussian noise: the joined estimate lies between the two and is
    # surer than the depth's alone.
    problem = lit_strip_corner(0.02, 0.02, 0.002, seed=3)
    depth = problem.solve(EstimateMethod.PLANES, with_amplitude=False, start_m2=0.02)
    joined = problem.solve(EstimateMethod.PLANES, start_m2=0.02)
    light = problem.with_fixed_planes._fit_amplitude(EstimateMethod.PLANES, start_m2=0.02)
    assert light.area_m2 == pytest.approx(0.02, rel=0.05) and joined.area_m2 == pytest.approx(0.02, rel=0.1)
    low, high = sorted([depth.area_m2, light.area_m2])
    assert low < joined.area_m2 < high
    assert joined.sigma_m2 / joined.area_m2 < depth.sigma_m2 / depth.area_m2
    assert joined.significant
    # The two measurements it joined (the amplitude's fit starts from the depth's estimate: within its 1 % step).
    assert joined.depth_m2 == depth.area_m2 and joined.amplitude_m2 == pytest.approx(light.area_m2, rel=0.01)
    assert joined.disagreement == pytest.approx(high / low, rel=0.01)


@pytest.mark.unit
def test_estimate__an_amplitude_that_shows_no_multipath_makes_the_depths_estimate_not_significant():
    # The depth says 0.02 m^2, the light says a tenth of it: the model does not describe this scan.
    problem = lit_strip_corner(0.02, 0.002, 0.001, seed=3)
    depth = problem.solve(EstimateMethod.PLANES, with_amplitude=False, start_m2=0.02)
    found = problem.solve(EstimateMethod.PLANES, start_m2=0.02)
    assert depth.significant and not found.significant
    assert found.area_m2 == depth.area_m2 and found.sigma_m2 >= found.area_m2
