"""Ranges past the combined ambiguity told by the continuity of surfaces: wrap seams and regions flagged by their
amplitude, and the dark near surfaces and lone noisy pixels that must not be."""

from __future__ import annotations

import numpy as np
import pytest

from benchmarks.sensor_law import SENSOR, law_model, made_scan
from mpi_lidar.constants import SPEED_OF_LIGHT_M_PER_S
from mpi_lidar.correction import beyond_ambiguity
from mpi_lidar.correction.options import INVALID_FLAGS, CorrectionOptions, Flag
from mpi_lidar.correction.tiles import scan_tiles
from mpi_lidar.correction.validity import BeyondAmbiguity, check_validity
from mpi_lidar.physics.unwrap import combined_ambiguity_m

pytestmark = pytest.mark.unit

SIDE = 48


def _flags(range_m: np.ndarray, albedo: float, law: str = "shot 2.5x", unit_known: bool = True) -> np.ndarray:
    """The validity flags (H, W) of a scan of surfaces facing the sensor at ``range_m`` (H, W) [m], with the law's
    own noise model, the test past the ambiguity given the unit (or not)."""
    noise = law_model(law)
    scan, _ = made_scan("scene", range_m, albedo, noise, 3)
    ambiguity = combined_ambiguity_m(noise.frequencies_hz, SPEED_OF_LIGHT_M_PER_S)
    beyond = BeyondAmbiguity(ambiguity, SENSOR.gamma_r_v2 if unit_known else None)
    validity = check_validity(scan, noise, CorrectionOptions(), scan_tiles(scan, 10**6), beyond=beyond)
    return validity.flags.reshape(range_m.shape)


def _ramp(near_m: float, far_m: float) -> np.ndarray:
    return np.repeat(np.linspace(near_m, far_m, SIDE)[None], SIDE, axis=0)


@pytest.mark.parametrize("law", ["shot 2.5x", "read-dominated"])
def test_check_validity__a_surface_through_the_ambiguity_is_flagged_past_its_wrap_seam(law):
    range_m = _ramp(16.0, 32.0)
    flags = _flags(range_m, 0.7, law)
    past = range_m > 24.2
    reported = ~np.isin(flags, INVALID_FLAGS) & (flags != Flag.AMBIGUOUS)
    assert not reported[past].any(), "no pixel past the ambiguity reported at its near range"
    # Read noise leaves the farthest pixels too little light at all frequencies together for any range.
    assert np.isin(flags[past], [Flag.BEYOND_AMBIGUITY, Flag.NO_RETURN]).mean() > 0.99
    assert (flags[past] == Flag.BEYOND_AMBIGUITY).mean() > (0.9 if law == "shot 2.5x" else 0.15)
    assert (flags[range_m < 23.8] == Flag.BEYOND_AMBIGUITY).mean() < 0.01


def test_check_validity__continuity_needs_no_unit():
    range_m = _ramp(16.0, 32.0)
    flags = _flags(range_m, 0.7, unit_known=False)
    assert (flags[range_m > 24.2] == Flag.BEYOND_AMBIGUITY).mean() > 0.9
    assert not (flags[range_m < 23.8] == Flag.BEYOND_AMBIGUITY).any()


def test_check_validity__a_bright_wall_past_the_ambiguity_has_no_valid_pixel():
    flags = _flags(np.full((SIDE, SIDE), 26.0), 0.9)
    assert (flags == Flag.BEYOND_AMBIGUITY).all()


@pytest.mark.parametrize("law", ["shot 2.5x", "read-dominated"])
def test_check_validity__dark_near_surfaces_are_not_flagged(law):
    assert (_flags(_ramp(0.5, 4.0), 0.03, law) == Flag.BEYOND_AMBIGUITY).mean() <= 0.01
    # A 2 % wall at 4 m reads as a white one at 28 m: its noisiest pixels may be flagged one by one, but the
    # surface does not follow them.
    assert (_flags(np.full((SIDE, SIDE), 4.0), 0.02, law) == Flag.BEYOND_AMBIGUITY).mean() < 0.1


def test_check_validity__a_near_wall_beside_a_far_one_at_the_end_of_the_range_is_no_seam():
    range_m = np.full((SIDE, SIDE), 23.5)
    range_m[:, : SIDE // 2] = 1.0  # a bright near wall beside a far one: depths 1 and 23.5 m, amplitudes 550-fold
    flags = _flags(range_m, 0.7)
    assert not (flags == Flag.BEYOND_AMBIGUITY).any()


@pytest.mark.parametrize("transpose", [False, True], ids=["seam across the bands", "seam along a band's edge"])
def test_check_validity__continuity_worked_out_in_bands_of_rows_flags_as_the_whole_scan(monkeypatch, transpose):
    range_m = _ramp(16.0, 32.0)
    range_m = range_m.T if transpose else range_m
    whole = _flags(range_m, 0.7)
    # 5 rows a band: 10 bands, the last one short, the seam (or the surface's rows) split between them.
    monkeypatch.setattr(beyond_ambiguity, "BAND_PIXELS", 5 * SIDE)
    banded = _flags(range_m, 0.7)
    assert (whole == Flag.BEYOND_AMBIGUITY).mean() > 0.4
    np.testing.assert_array_equal(banded, whole)
