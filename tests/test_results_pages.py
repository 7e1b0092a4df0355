"""The results pages: each states its latest run, its command and date in under 12 KiB, with no dated history;
benchmarks.results replaces a page's latest-run block with a benchmark's run and keeps the rest of the page."""

from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path

import pytest

from benchmarks.results import BEGIN, END, PAGES, latest_block, with_latest

DOCS = Path(__file__).resolve().parent.parent / "docs" / "results"
RESULTS_PAGES = sorted(DOCS.glob("*.md"))
# A results page states what holds now (the latest run, how it is measured, what it shows); history lives in git.
PAGE_LIMIT_BYTES = 12 * 1024
PAGE = "# Results: x\n\n**Regenerate:** `cmd`\n\n## Earlier, 2026-11-20\n\n| a |\n|---|\n| 1 |\n"


@pytest.mark.unit
def test_with_latest__a_page_without_the_block_gets_it_after_its_first_paragraph():
    page = with_latest(PAGE, latest_block("python -m b", "| new |"))
    assert page.index("**Regenerate:**") < page.index(BEGIN) < page.index("| new |") < page.index(END)
    assert page.index(END) < page.index("## Earlier, 2026-11-20") and page.endswith("| 1 |\n")


@pytest.mark.unit
def test_with_latest__a_second_run_replaces_the_first_and_keeps_the_rest():
    once = with_latest(PAGE, latest_block("python -m b", "| first |"))
    twice = with_latest(once, latest_block("python -m b", "| second |"))
    assert "| first |" not in twice and twice.count(BEGIN) == 1 and "| second |" in twice
    assert twice.replace(latest_block("python -m b", "| second |"), "") == once.replace(
        latest_block("python -m b", "| first |"), "")


@pytest.mark.integration
def test_pages__every_page_has_its_file_and_its_benchmark_module():
    for page, module in PAGES.items():
        assert (DOCS / f"{page}.md").is_file(), page
        assert (Path(__file__).resolve().parent.parent / (module.replace(".", "/") + ".py")).is_file(), module


@pytest.mark.unit
@pytest.mark.parametrize("page", RESULTS_PAGES, ids=lambda p: p.name)
def test_results_page__under_12_kib(page):
    size = page.stat().st_size
    assert size < PAGE_LIMIT_BYTES, f"{page.name}: {size} bytes, at most {PAGE_LIMIT_BYTES - 1}"


@pytest.mark.unit
@pytest.mark.parametrize("page", RESULTS_PAGES, ids=lambda p: p.name)
def test_results_page__states_its_command_and_the_date_of_its_run(page):
    text = page.read_text()
    assert re.search(r"`(OMP_NUM_THREADS=1 )?(\.venv/bin/python -m |mpi-lidar )", text), f"{page.name}: no command"
    assert re.search(r"\b20\d\d-\d\d-\d\d\b", text), f"{page.name}: no date"


@pytest.mark.unit
@pytest.mark.parametrize("page", RESULTS_PAGES, ids=lambda p: p.name)
def test_results_page__has_no_dated_or_earlier_sections(page):
    headings = re.findall(r"^#+ (.*)$", page.read_text(), flags=re.M)
    dated = [h for h in headings if re.search(r"\b20\d\d-\d\d-\d\d\b|^earlier\b", h, flags=re.I)]
    assert not dated, f"{page.name}: {dated}"


@pytest.mark.integration
def test_results_command__runs_the_benchmark_and_a_failure_leaves_the_page(tmp_path):
    (tmp_path / "limits.md").write_text(PAGE)
    run = [sys.executable, "-m", "benchmarks.results", "limits", "--docs", str(tmp_path), "--"]
    small = ["--n-test", "20", "--pool", "100", "--scales", "1"]
    done = subprocess.run([*run, *small], capture_output=True, text=True, check=False)
    assert done.returncode == 0, done.stderr
    page = (tmp_path / "limits.md").read_text()
    assert f"python -m benchmarks.limits {' '.join(small)}" in page and "|---" in page and "## Earlier" in page
    failed = subprocess.run([*run, "--n-test", "not-a-number"], capture_output=True, text=True, check=False)
    assert failed.returncode != 0 and "unchanged" in failed.stderr
    assert (tmp_path / "limits.md").read_text() == page
