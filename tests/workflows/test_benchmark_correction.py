"""The correction benchmark runs at tiny sizes and prints its tables (columns checked, not timings)."""

from __future__ import annotations

import pytest

from benchmarks import correction as bench

pytestmark = pytest.mark.integration


@pytest.mark.slow
def test_benchmark_correction__quick_prints_every_table(tmp_path):
    text = bench.run(bench.Plan.quick(), None, tmp_path)
    assert text.startswith("Machine: ") and "cores" in text and "load average" in text
    tables = [block.splitlines() for block in text.split("\n\n") if block.startswith("| ")]
    headers = [tuple(cell.strip() for cell in lines[0].strip("|").split("|")) for lines in tables]
    assert headers[:5] == [bench.STAGE_HEADERS, bench.END_TO_END_HEADERS, bench.INFERENCE_HEADERS,
                           bench.BATCH_HEADERS, bench.MEMORY_HEADERS]
    assert [header[0] for header in headers[5:]] == ["what", "outputs"], "the start-up and its heavy imports"
    startup = [line.split("|")[1].strip() for line in tables[5][2:]]
    assert "`correct --outputs light`: whole - warm scan" in startup and len(startup) == 9
    assert [line.split("|")[1].strip() for line in tables[6][2:]] == ["data", "light"]
    stages = [line.split("|")[1].strip() for line in tables[0][2:]]
    for stage in ("read", "validity", "gate", "features", "inference", "write (light)", "figures (light)",
                  "write (full)", "figures (full)"):
        assert stage in stages
    assert len(tables[1]) == 2 + 4, "three output levels and the command line"
    assert all(len(lines) == 2 + rows for lines, rows in zip(tables[2:5], (1, 2, 2), strict=True))
    for lines in tables:
        assert all(line.count("|") == lines[0].count("|") for line in lines)
