"""The docs' lists of the files each output level (``--outputs``) writes are made from one registry,
:data:`mpi_lidar.reporting.output_levels.OUTPUT_FILES` (docs/output_files.py writes them): a page that disagrees
with it fails here, and the registry itself is what the outputs hold (tests/reporting/test_scan_outputs.py)."""

from __future__ import annotations

import importlib.util
import re
from dataclasses import replace
from pathlib import Path

import pytest

from mpi_lidar.reporting import output_levels
from mpi_lidar.reporting.output_levels import OUTPUT_FILES, OUTPUT_LEVELS, OutputLevel, level_files
from mpi_lidar.workflows.batch_options import BatchOptions

ROOT = Path(__file__).resolve().parents[2]
# The pages that list a level's files, and the blocks each holds.
LISTING_PAGES = {"docs/how-to/batch-correct.md": {"table"},
                 "docs/tutorial/first-correction.md": {"full"}}


def _generator():
    spec = importlib.util.spec_from_file_location("output_files", ROOT / "docs" / "output_files.py")
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


GENERATOR = _generator()


@pytest.mark.unit
@pytest.mark.parametrize("page", GENERATOR.pages(ROOT), ids=lambda page: page.relative_to(ROOT).as_posix())
def test_output_files_blocks__every_page_as_the_registry_makes_it(page):
    text = page.read_text()
    assert GENERATOR.refreshed(text, page) == text, f"{page} is out of date: run .venv/bin/python docs/output_files.py"


@pytest.mark.unit
@pytest.mark.parametrize(("page", "kinds"), LISTING_PAGES.items())
def test_output_files_blocks__each_listing_page_has_its_blocks_and_they_follow_the_registry(page, kinds, monkeypatch):
    path = ROOT / page
    text = path.read_text()
    assert {found["kind"] for found in GENERATOR.MARKED.finditer(text)} == kinds
    # A file added to the registry at the lowest level shows on every block of the page.
    monkeypatch.setattr(output_levels, "OUTPUT_FILES", (*OUTPUT_FILES, replace(OUTPUT_FILES[0], name="new.bin")))
    changed = GENERATOR.refreshed(text, path)
    assert all("`new.bin`" in found["body"] for found in GENERATOR.MARKED.finditer(changed))


@pytest.mark.unit
def test_output_files__the_registry_is_what_each_level_writes():
    from tests.reporting.test_scan_outputs import FILES  # checked there against a corrected scan's files

    assert {level: {file.name for file in level_files(level)} for level in OUTPUT_LEVELS} == FILES
    assert len({file.name for file in OUTPUT_FILES}) == len(OUTPUT_FILES)


@pytest.mark.unit
def test_outputs_help__names_each_levels_files_from_the_registry():
    said = BatchOptions.model_fields["outputs"].description or ""
    for file in OUTPUT_FILES:
        assert re.search(rf"{re.escape(file.name)}[^()]* \({file.level.value}\b", said), (file.name, said)


@pytest.mark.unit
def test_point_clouds_page__the_levels_that_write_each_file_are_the_registrys():
    """docs/reference/point-clouds.md's column "written by default" names the levels the registry gives."""
    rows = [line.split("|") for line in (ROOT / "docs/reference/point-clouds.md").read_text().splitlines()
            if line.startswith("| `")]
    checked = 0
    for row in rows:
        name, said = row[1].strip().strip("`"), row[-2]
        named = {level.value for level in OutputLevel if f"`--outputs {level.value}`" in said or
                 f"`{level.value}`" in said or f" {level.value} " in said}
        if name in {file.name for file in OUTPUT_FILES} and named:
            assert named == {level for level in OUTPUT_LEVELS if name in {f.name for f in level_files(level)}}, row
            checked += 1
    assert checked >= 2
