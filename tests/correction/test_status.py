"""The status stage: why a model could not serve a scan, from its flags."""

from __future__ import annotations

import numpy as np
import pytest

from mpi_lidar.correction.options import CorrectionOptions, Flag, UnservedReason
from mpi_lidar.correction.status import AMBIGUOUS_SHARE, SATURATED_UNITS_SHARE, unserved_reason, untrusted_unit

pytestmark = pytest.mark.unit

RANGE = (1.4, 2.4)


def _flags(**shares: float) -> np.ndarray:
    """1000 flags: the given share of each named flag, the rest corrected."""
    flags = np.full(1000, Flag.CORRECTED, np.uint8)
    start = 0
    for name, share in shares.items():
        count = round(1000 * share)
        flags[start:start + count] = Flag[name.upper()]
        start += count
    return flags


def test_unserved_reason__a_served_scan_has_none():
    assert unserved_reason(_flags(no_multipath=0.5), RANGE, CorrectionOptions()) is None


def test_unserved_reason__each_cause_above_its_share_in_order():
    options = CorrectionOptions()
    saturated = unserved_reason(_flags(saturated=SATURATED_UNITS_SHARE + 0.01), RANGE, options)
    assert saturated is not None and saturated.reason == UnservedReason.AMPLITUDE_UNITS
    assert unserved_reason(_flags(saturated=SATURATED_UNITS_SHARE - 0.01), RANGE, options) is None
    blind = unserved_reason(_flags(), RANGE, options, served=False)
    assert blind is not None and blind.reason == UnservedReason.NO_GEOMETRY
    ambiguous = unserved_reason(_flags(ambiguous=AMBIGUOUS_SHARE + 0.01), RANGE, options)
    assert ambiguous is not None and ambiguous.reason == UnservedReason.AMBIGUOUS_RANGE
    far = unserved_reason(_flags(out_of_range=0.3, no_multipath=0.7), RANGE, options)
    assert far is not None and far.reason == UnservedReason.OUT_OF_RANGE and "1.4-2.4 m" in far.message
    assert unserved_reason(_flags(out_of_range=0.3), RANGE, options) is None, "some corrected: served"


def test_unserved_reason__not_finite_pixels_do_not_count_towards_the_shares():
    flags = _flags(not_finite=0.5, saturated=0.46)
    assert unserved_reason(flags, RANGE, CorrectionOptions()).reason == UnservedReason.AMPLITUDE_UNITS


def test_untrusted_unit__says_why_and_what_helps():
    why = untrusted_unit("surfaces 4000 times brighter than white")
    assert why.reason == UnservedReason.AMPLITUDE_UNITS and "4000 times brighter" in why.message
    assert "--amplitude-scale" in why.message and "fused depths are written" in why.message
