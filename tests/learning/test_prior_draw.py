"""The default training prior's draw: log-uniform coupling, its reach, and the Bayes limit's density of it."""

from __future__ import annotations

import numpy as np
import pytest

from mpi_lidar.config import Config, PriorConfig, preset
from mpi_lidar.learning.limits import log_coupling_density
from mpi_lidar.learning.model_card import PriorCard
from mpi_lidar.simulation.sampling import THETA_NAMES, sample_theta

RHO_ABA = THETA_NAMES.index("rho_aba")


@pytest.mark.unit
def test_sample_theta__log_uniform_coupling_puts_as_many_rows_in_every_octave():
    prior = PriorConfig(coupling=(0.01, 2.56), coupling_distribution="log_uniform", albedo=(1.0, 1.0))
    rho_aba = sample_theta(prior, 80_000, np.random.default_rng(0))[:, RHO_ABA]  # = kappa with a white partner
    octaves = np.histogram(rho_aba, bins=0.01 * 2.0 ** np.arange(9))[0] / rho_aba.size
    np.testing.assert_allclose(octaves, 1 / 8, atol=0.006)  # 8 octaves, binomial sd 0.0012
    assert rho_aba.min() >= 0.01 and rho_aba.max() <= 2.56


@pytest.mark.unit
def test_log_coupling_density__is_the_density_of_the_draw():
    prior = Config().prior
    q = sample_theta(prior, 200_000, np.random.default_rng(1))[:, RHO_ABA]
    edges = np.array([0.002, 0.01, 0.05, 0.2, 0.5, 1.0, 1.5, 2.0])
    share = np.histogram(q, bins=edges)[0] / q.size
    grid = np.linspace(edges[0], edges[-1], 400_001)
    density = np.exp(log_coupling_density(grid, prior))
    cdf = np.concatenate([[0.0], np.cumsum((density[1:] + density[:-1]) / 2 * np.diff(grid))])
    expected = np.diff(np.interp(edges, grid, cdf))
    np.testing.assert_allclose(share, expected, atol=0.004)


@pytest.mark.unit
def test_wide_preset__reaches_the_scenes_and_the_default_and_paper_keep_the_paper_s_multipath():
    assert PriorCard(**preset("wide").prior.model_dump(mode="json")).multipath_reach() == (2.0, 0.6)
    assert PriorCard(**Config().prior.model_dump(mode="json")).multipath_reach() == (1.0, 0.15)
    paper = preset("paper").prior
    assert PriorCard(**paper.model_dump(mode="json")).multipath_reach() == (1.0, 0.15)
    assert paper.coupling_distribution == "uniform" and "coupling_distribution" not in paper.model_dump()


@pytest.mark.unit
def test_sample_theta__a_uniform_coupling_draws_the_numbers_it_always_drew():
    prior = PriorConfig()
    theta = sample_theta(prior, 1_000, np.random.default_rng(5))
    rng = np.random.default_rng(5)
    d_as, d_ab = rng.uniform(1.4, 2.4, 1_000), rng.uniform(0.0, 0.15, 1_000)
    albedo_a, albedo_b = rng.uniform(0.14, 1.0, 1_000), rng.uniform(0.14, 1.0, 1_000)
    coupling = rng.uniform(0.0, 1.0, 1_000)
    np.testing.assert_array_equal(theta, np.column_stack([d_as, d_ab, albedo_a, albedo_a, coupling * albedo_b,
                                                          albedo_a]))


@pytest.mark.unit
def test_prior_config__refuses_a_log_uniform_coupling_from_zero():
    with pytest.raises(ValueError, match="log-uniform coupling_distribution needs coupling low > 0"):
        PriorConfig(coupling=(0.0, 2.0), coupling_distribution="log_uniform")
