"""Scene-parameter priors: named schemes that draw theta = (d_AS, d_AB, rho_SAS, rho_SAB, rho_ABA, rho_BAS).

The paper says only that each rho lies in 0-1. Independent uniform draws give a raw 31.25 MHz MAE near
17 mm and an unbounded tail as rho_SAS -> 0; the reciprocal scheme (one albedo for the three reflections at
A, a coupling for the one at B) lands on the paper's 9.857 mm and is the default.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
from numpy.typing import NDArray

from mpi_lidar.config import PriorConfig

THETA_NAMES = ("d_as_m", "d_ab_m", "rho_sas", "rho_sab", "rho_aba", "rho_bas")


def _uniform(rng: np.random.Generator, interval: tuple[float, float], n: int) -> NDArray[np.float64]:
    return rng.uniform(interval[0], interval[1], n)


def _log_uniform(rng: np.random.Generator, interval: tuple[float, float], n: int) -> NDArray[np.float64]:
    """n values of density 1 / (x ln(high / low)) over ``interval`` (low > 0): as many in every octave."""
    low, high = interval
    # exp(ln x) may round one ulp past an end; the clip keeps every draw inside the prior's support.
    return np.clip(np.exp(rng.uniform(np.log(low), np.log(high), n)), low, high)


def _drawn(rng: np.random.Generator, interval: tuple[float, float], n: int, distribution: str
           ) -> NDArray[np.float64]:
    """n values over ``interval``, uniform or log-uniform. Both take one uniform draw of n values, so a uniform
    prior draws exactly the numbers it always drew."""
    return _uniform(rng, interval, n) if distribution == "uniform" else _log_uniform(rng, interval, n)


def _d_as(prior: PriorConfig, n: int, rng: np.random.Generator) -> NDArray[np.float64]:
    """n direct depths d_AS from ``prior.d_as_m`` as ``prior.d_as_distribution`` says. [m]"""
    return _drawn(rng, prior.d_as_m, n, prior.d_as_distribution)


def _reciprocal(prior: PriorConfig, n: int, rng: np.random.Generator) -> NDArray[np.float64]:
    d_as, d_ab = _d_as(prior, n, rng), _uniform(rng, prior.d_ab_m, n)
    albedo_a, albedo_b = _uniform(rng, prior.albedo, n), _uniform(rng, prior.albedo, n)
    coupling = _drawn(rng, prior.coupling, n, prior.coupling_distribution)
    return np.column_stack([d_as, d_ab, albedo_a, albedo_a, coupling * albedo_b, albedo_a])


def _independent(prior: PriorConfig, n: int, rng: np.random.Generator) -> NDArray[np.float64]:
    d_as, d_ab = _d_as(prior, n, rng), _uniform(rng, prior.d_ab_m, n)
    return np.column_stack([d_as, d_ab, *(_uniform(rng, prior.rho, n) for _ in range(4))])


def _explicit(prior: PriorConfig, n: int, rng: np.random.Generator) -> NDArray[np.float64]:
    d_as, d_ab = _d_as(prior, n, rng), _uniform(rng, prior.d_ab_m, n)
    rhos = (prior.rho_sas, prior.rho_sab, prior.rho_aba, prior.rho_bas)
    return np.column_stack([d_as, d_ab, *(_uniform(rng, r, n) for r in rhos)])


SCHEMES: dict[str, Callable[[PriorConfig, int, np.random.Generator], NDArray[np.float64]]] = {
    "reciprocal": _reciprocal,
    "independent": _independent,
    "explicit": _explicit,
}


def sample_theta(prior: PriorConfig, n: int, rng: np.random.Generator) -> NDArray[np.float64]:
    """Draw n scene parameter vectors, shape (n, 6), columns :data:`THETA_NAMES`. [m, m, 1, 1, 1, 1]

    d_AS is uniform or log-uniform over ``prior.d_as_m`` (``prior.d_as_distribution``), drawn first in every
    scheme; the reciprocal scheme's coupling is uniform or log-uniform over ``prior.coupling``
    (``prior.coupling_distribution``). With ``prior.no_multipath_fraction`` > 0 each row independently loses its
    multipath (rho_ABA = 0) with that probability, drawn after the scheme's columns (a fraction of 0 draws nothing
    more, so the paper's prior gives the same rows as before).
    """
    theta = SCHEMES[prior.scheme](prior, n, rng)
    if prior.no_multipath_fraction > 0:
        theta[rng.random(n) < prior.no_multipath_fraction, THETA_NAMES.index("rho_aba")] = 0.0
    return theta
