"""A correction's notes in words, from the stages' results."""

from __future__ import annotations

import numpy as np
import pytest

from mpi_lidar.config import PAPER_FREQUENCIES_HZ, SensorConfig
from mpi_lidar.correction.baseline import FrequencyOffsets, OffsetSource
from mpi_lidar.correction.footprint import FootprintEstimate
from mpi_lidar.correction.result import Correction
from mpi_lidar.correction.sensor_reading import SensorReading
from mpi_lidar.physics.noise import NoiseModel
from mpi_lidar.physics.noise_law import NoiseLaw
from mpi_lidar.reporting.correction_notes import correction_notes, offsets_mm, reading_notes

pytestmark = pytest.mark.unit

MAPS = {"depth": np.zeros((2, 2), np.float32), "flags": np.zeros((2, 2), np.uint8)}


def test_correction_notes__nothing_to_say_for_a_plain_correction():
    assert correction_notes(Correction(**MAPS)) == ()


def _reading(law: NoiseLaw | None, given: bool = False, contradiction: str = "") -> SensorReading:
    noise = NoiseModel.for_sensor(SensorConfig(), PAPER_FREQUENCIES_HZ)
    return SensorReading(4000.0 if given else 1.0, given, contradiction, law, noise, np.full(4, np.inf))


def test_correction_notes__each_stage_in_order():
    law = NoiseLaw(1.02, 0.98, 0.02, 0.03, 9000, 0.02, True)
    footprint = FootprintEstimate(0.031, 0.004, 1200, 2)
    offsets = FrequencyOffsets(np.array([0.0011, 0.0, -0.0002, 0.0]), True, OffsetSource.MEASURED,
                               np.array([0.0015, 0.0001, -0.0001, 0.0]))
    notes = correction_notes(Correction(**MAPS, reading=_reading(law), scene_notes=("a scene note",),
                                        calibration=footprint, beyond_prior_pixels=17, prior_reach=(1.0, 0.15),
                                        offsets=offsets))
    assert len(notes) == 6
    assert notes[0].startswith("noise law: measured on 9,000 pixels") and "read noise 1.02 +- 0.02" in notes[0]
    assert notes[1].startswith("amplitude unit: V^2 (not given")
    assert notes[2] == "a scene note"
    assert notes[3].startswith("footprint auto: 0.031 +- 0.004 m^2 from 1,200 pixels on 2 surfaces")
    assert notes[4].startswith("17 corrected pixels have multipath beyond") and "rho_ABA above 1 " in notes[4]
    assert "+1.100, +0.000, -0.200, +0.000 mm" in notes[5] and "leakage removed first" in notes[5]
    assert "+1.500, +0.100, -0.100, +0.000 mm otherwise" in notes[5]


def test_correction_notes__a_footprint_whose_depth_and_amplitude_disagree_says_so():
    apart = FootprintEstimate(0.031, 0.004, 1200, 2, depth_m2=0.02, amplitude_m2=0.04)
    (note,) = correction_notes(Correction(**MAPS, calibration=apart))
    assert note.endswith("its depth and amplitude measured 0.02 and 0.04 m^2, 2x apart: the footprint, and the "
                         "correction near edges, may be off by as much")
    for close in (FootprintEstimate(0.031, 0.004, 1200, 2, depth_m2=0.030, amplitude_m2=0.032),
                  FootprintEstimate(0.031, 0.004, 1200, 2)):  # agreeing, or no amplitude fitted
        (note,) = correction_notes(Correction(**MAPS, calibration=close))
        assert note.endswith("the coupling and the gate use it")


def test_reading_notes__a_unit_given_contradicted_or_a_law_not_measured():
    unmeasured = NoiseLaw(float("nan"), float("nan"), float("inf"), float("inf"), 12, float("inf"), False, "too few")
    law, unit = reading_notes(_reading(unmeasured, given=True))
    assert law == "noise law: not measured (too few); the sensor model's is used"
    assert unit == "amplitude unit: 4000 per V^2, as given"
    _, contradicted = reading_notes(_reading(None, contradiction="too bright"))
    assert "not V^2 (too bright)" in contradicted and "model was not applied" in contradicted


def test_correction_notes__offsets_not_measured_say_why_and_a_profiles_say_nothing():
    for source, said in ((OffsetSource.NO_GEOMETRY, "no scene geometry"), (OffsetSource.TOO_FEW_PIXELS, "fewer")):
        (note,) = correction_notes(Correction(**MAPS, offsets=FrequencyOffsets(source=source)))
        assert note.startswith("frequency offsets: not measured") and said in note
    profile = FrequencyOffsets(np.zeros(4), False, OffsetSource.PROFILE)
    assert correction_notes(Correction(**MAPS, offsets=profile)) == ()


def test_offsets_mm__signed_millimetres():
    assert offsets_mm((0.0012345, -0.0001)) == "+1.234, -0.100"
