"""The one registry of what flags and estimates mean: complete, and the docs' tables made from it."""

from __future__ import annotations

from pathlib import Path

import pytest

from mpi_lidar.correction.options import INVALID_FLAGS, Estimate, Flag
from mpi_lidar.reporting.legend import (
    DOC_PAGES,
    ESTIMATE_LEGEND,
    FLAG_LEGEND,
    doc_tables,
    flag_record,
    refreshed,
)

pytestmark = pytest.mark.unit

ROOT = Path(__file__).resolve().parents[2]


def test_legend__every_flag_and_estimate_once_with_its_own_letter_and_colour():
    assert set(FLAG_LEGEND) == set(Flag) and set(ESTIMATE_LEGEND) == set(Estimate)
    assert len({e.letter for e in FLAG_LEGEND.values()}) == len(Flag)
    assert len({e.colour for e in FLAG_LEGEND.values()}) == len(Flag)
    record = flag_record()
    assert {int(code) for code, entry in record.items() if entry["invalid"]} == {int(f) for f in INVALID_FLAGS}
    # a valid pixel the model leaves alone holds the baseline: the fused frequencies by default
    for flag in (Flag.NOT_NEEDED, Flag.OUT_OF_RANGE, Flag.NO_MULTIPATH, Flag.UNCALIBRATED):
        assert "fused" in record[str(int(flag))]["depth"] and "raw range kept" not in record[str(int(flag))]["meaning"]


@pytest.mark.parametrize("page", DOC_PAGES)
def test_docs__flag_tables_are_the_registry_s(page):
    text = (ROOT / page).read_text()
    assert refreshed(text) == text, f"{page} is out of date: run `.venv/bin/python -m mpi_lidar.reporting.legend`"
    assert any(f"<!-- legend:{name} -->" in text for name in doc_tables())
