"""A correction's notes in words, from the stages' results."""

from __future__ import annotations

import numpy as np
import pytest

from mpi_lidar.correction.amplitude_unit import AmplitudeUnit
from mpi_lidar.correction.baseline import FrequencyOffsets, OffsetSource
from mpi_lidar.correction.footprint import FootprintEstimate
from mpi_lidar.correction.result import Correction
from mpi_lidar.reporting.correction_notes import correction_notes, offsets_mm

pytestmark = pytest.mark.unit

MAPS = {"depth": np.zeros((2, 2), np.float32), "flags": np.zeros((2, 2), np.uint8)}


def test_correction_notes__nothing_to_say_for_a_plain_correction():
    assert correction_notes(Correction(**MAPS)) == ()


def test_correction_notes__each_stage_in_order():
    unit = AmplitudeUnit(4012.0, 0.012, 9000, True)
    footprint = FootprintEstimate(0.031, 0.004, 1200, 2)
    offsets = FrequencyOffsets(np.array([0.0011, 0.0, -0.0002, 0.0]), True, OffsetSource.MEASURED,
                               np.array([0.0015, 0.0001, -0.0001, 0.0]))
    notes = correction_notes(Correction(**MAPS, amplitude_unit=unit, scene_notes=("a scene note",),
                                        calibration=footprint, beyond_prior_pixels=17, prior_reach=(1.0, 0.15),
                                        offsets=offsets))
    assert len(notes) == 5
    assert notes[0].startswith("amplitude unit auto: 4012 +- 48 per V^2") and notes[0].endswith("divided by it")
    assert notes[1] == "a scene note"
    assert notes[2].startswith("footprint auto: 0.031 +- 0.004 m^2 from 1,200 pixels on 2 surfaces")
    assert notes[3].startswith("17 corrected pixels have multipath beyond") and "rho_ABA above 1 " in notes[3]
    assert "+1.100, +0.000, -0.200, +0.000 mm" in notes[4] and "leakage removed first" in notes[4]
    assert "+1.500, +0.100, -0.100, +0.000 mm otherwise" in notes[4]


def test_correction_notes__offsets_not_measured_say_why_and_a_profiles_say_nothing():
    for source, said in ((OffsetSource.NO_GEOMETRY, "no scene geometry"), (OffsetSource.TOO_FEW_PIXELS, "fewer")):
        (note,) = correction_notes(Correction(**MAPS, offsets=FrequencyOffsets(source=source)))
        assert note.startswith("frequency offsets: not measured") and said in note
    profile = FrequencyOffsets(np.zeros(4), False, OffsetSource.PROFILE)
    assert correction_notes(Correction(**MAPS, offsets=profile)) == ()


def test_offsets_mm__signed_millimetres():
    assert offsets_mm((0.0012345, -0.0001)) == "+1.234, -0.100"
