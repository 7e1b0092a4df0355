"""The mixed-pixel stage: flying pixels at depth edges flagged, resolved into two returns where the data allow,
and a scan without depth edges left exactly as the gate left it."""

from __future__ import annotations

import numpy as np
import pytest

from mpi_lidar.config import Config, SensorConfig
from mpi_lidar.correction.gating import GateDecision
from mpi_lidar.correction.mixed import find_mixed
from mpi_lidar.correction.options import CorrectionOptions, Flag
from mpi_lidar.correction.tiles import scan_tiles
from mpi_lidar.correction.validity import check_validity
from mpi_lidar.physics.noise import NoiseModel
from mpi_lidar.physics.two_returns import evenly_spaced, fit_two_returns
from mpi_lidar.simulation.scenes import scan_from_phasors

pytestmark = pytest.mark.unit

CONFIG = Config()
EDGE_COLUMN = 6


def _plate_scan(plate_m: float, plate_albedo: float, wall_m: float, wall_albedo: float, plate_share: float,
                seed: int = 0, height: int = 16, width: int = 14):
    """Plate on the left, wall on the right, and one column between whose footprint holds ``plate_share`` of
    plate, its phasor the sum of both surfaces'."""
    freqs = np.asarray(CONFIG.frequencies_hz)
    w = 4 * np.pi * freqs / CONFIG.sensor.speed_of_light_m_per_s
    gamma = CONFIG.sensor.gamma_r_v2
    plate = gamma * plate_albedo / plate_m**2 * np.exp(1j * w * plate_m)
    wall = gamma * wall_albedo / wall_m**2 * np.exp(1j * w * wall_m)
    share = np.where(np.arange(width) < EDGE_COLUMN, 1.0, 0.0)
    share[EDGE_COLUMN] = plate_share
    phasor = share[None, None, :] * plate[:, None, None] + (1 - share)[None, None, :] * wall[:, None, None]
    phasor = np.broadcast_to(phasor, (freqs.size, height, width))
    return scan_from_phasors("plate", phasor, CONFIG, np.random.default_rng(seed))


def _stages(scan):
    noise = NoiseModel.for_sensor(SensorConfig(), scan.frequencies_hz)
    tiles = scan_tiles(scan, 5 * scan.shape[1])  # several tiles: the neighbours cross them
    validity = check_validity(scan, noise, CorrectionOptions(), tiles)
    flags = np.where(validity.flags == Flag.NOT_NEEDED, np.uint8(Flag.NO_MULTIPATH), validity.flags)
    decision = GateDecision(flags.astype(np.uint8), 0, served=True)
    return validity.scan, tiles, validity, decision, noise


def test_find_mixed__flags_the_edge_column_and_no_surface_pixel():
    scan, tiles, validity, decision, noise = _stages(_plate_scan(2.0, 0.05, 3.0, 1.0, 0.5))
    mixed = find_mixed(scan, tiles, validity, decision, noise)
    flags = mixed.decision.flags.reshape(scan.shape)
    assert (flags[:, EDGE_COLUMN] == Flag.MIXED).all()
    assert not np.isin(flags[:, [c for c in range(scan.shape[1]) if c != EDGE_COLUMN]],
                       [Flag.MIXED, Flag.TWO_RETURNS]).any()
    assert mixed.mixed_pixels == scan.shape[0] and mixed.resolved_pixels == 0 and mixed.second_returns is None
    assert np.isnan(mixed.validity.usable_depth.reshape(scan.shape)[:, EDGE_COLUMN]).all()
    assert validity.usable_depth.reshape(scan.shape)[:, EDGE_COLUMN].min() > 2.05  # a flying point, as measured


def test_find_mixed__resolves_two_returns_far_apart_into_the_stronger_depth_and_the_weaker_return():
    scan, tiles, validity, decision, noise = _stages(_plate_scan(2.0, 0.1, 9.0, 1.0, 0.5))
    mixed = find_mixed(scan, tiles, validity, decision, noise)
    flags = mixed.decision.flags.reshape(scan.shape)
    resolved = flags == Flag.TWO_RETURNS
    assert resolved[:, EDGE_COLUMN].mean() > 0.8 and not resolved[:, :EDGE_COLUMN].any()
    assert mixed.second_returns is not None
    usable = mixed.validity.usable_depth.reshape(scan.shape)
    np.testing.assert_allclose(usable[resolved], 2.0, atol=0.05)  # the plate holds 80 % of the light
    np.testing.assert_allclose(mixed.second_returns.depth_m[resolved], 9.0, atol=0.3)
    share = 0.5 / 81 / (0.5 / 81 + 0.05 / 4)
    np.testing.assert_allclose(mixed.second_returns.share[resolved], share, atol=0.05)
    assert np.isnan(mixed.second_returns.depth_m[~resolved]).all()


def test_find_mixed__a_scan_without_a_depth_edge_keeps_the_gate_s_decision_and_the_validity_as_they_are():
    scan, tiles, validity, decision, noise = _stages(_plate_scan(3.0, 1.0, 3.0, 1.0, 0.5))
    mixed = find_mixed(scan, tiles, validity, decision, noise)
    assert mixed.decision is decision and mixed.validity is validity
    assert mixed.mixed_pixels == mixed.resolved_pixels == 0 and mixed.second_returns is None


def test_fit_two_returns__recovers_both_returns_of_noiseless_phasors():
    freqs = np.asarray(CONFIG.frequencies_hz)
    c = CONFIG.sensor.speed_of_light_m_per_s
    w = 4 * np.pi * freqs / c
    z = 0.02 * np.exp(1j * w * 1.7) + 0.005 * np.exp(1j * w * 6.3)
    raw = np.concatenate([np.mod(np.angle(z), 2 * np.pi) / w, np.abs(z)])[None, :]
    fit = fit_two_returns(raw, freqs, np.full((1, freqs.size), 1e-4), c)
    np.testing.assert_allclose([fit.near_m[0], fit.far_m[0]], [1.7, 6.3], atol=1e-6)
    np.testing.assert_allclose([fit.stronger_m[0], fit.weaker_m[0], fit.weaker_share[0]], [1.7, 6.3, 0.2], atol=1e-6)
    assert fit.chi2[0] < 1e-6
    assert evenly_spaced(freqs) and not evenly_spaced([10e6, 20e6, 25e6, 40e6])
