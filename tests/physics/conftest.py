from __future__ import annotations

from collections.abc import Callable

import numpy as np
import pytest

from mpi_lidar.config import Config

FIDELITIES = ("moment", "waveform")


def make_scene(
    d_as: float | np.ndarray,
    d_ab: float | np.ndarray = 0.0,
    rho_sas: float | np.ndarray = 1.0,
    rho_sab: float | np.ndarray = 0.0,
    rho_aba: float | np.ndarray = 0.0,
    rho_bas: float | np.ndarray = 0.0,
) -> np.ndarray:
    """Scene parameters theta, shape (n, 6), broadcasting scalar and array arguments."""
    columns = np.broadcast_arrays(*(np.atleast_1d(np.asarray(x, dtype=np.float64))
                                    for x in (d_as, d_ab, rho_sas, rho_sab, rho_aba, rho_bas)))
    return np.column_stack(columns)


def make_reciprocal_scene(d_as, rho, d_ab=0.0, rho_aba=0.0) -> np.ndarray:
    """A scene of the reciprocal scheme: rho_SAS = rho_SAB = rho_BAS = rho."""
    return make_scene(d_as, d_ab, rho, rho, rho_aba, rho)


@pytest.fixture
def scene() -> Callable[..., np.ndarray]:
    return make_scene


@pytest.fixture
def reciprocal_scene() -> Callable[..., np.ndarray]:
    return make_reciprocal_scene


@pytest.fixture
def noiseless() -> Callable[..., Config]:
    """Factory: the default configuration without noise and without photon rounding."""

    def factory(fidelity: str = "moment", **simulator: object) -> Config:
        options = {"noise_scale": 0.0, "round_photons": False, "fidelity": fidelity, **simulator}
        return Config().replace(simulator=options)

    return factory


@pytest.fixture(params=FIDELITIES)
def fidelity(request: pytest.FixtureRequest) -> str:
    return request.param
