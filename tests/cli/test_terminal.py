"""What the command line prints: plain tables and occasional progress lines when piped, rich ones on a terminal,
one line per usage error."""

from __future__ import annotations

import io
import os
import time

import pytest

from mpi_lidar.terminal import Display, duration, plain_text, plural, print_table, table_lines
from tests.cli_runner import assert_one_error_line, call_main

pytestmark = pytest.mark.unit


class FakeTerminal(io.StringIO):
    def isatty(self) -> bool:
        return True


def test_plural__one_and_many():
    assert [plural(n, "scan") for n in (0, 1, 2, 1000)] == ["0 scans", "1 scan", "2 scans", "1,000 scans"]
    assert plural(2, "study", "studies") == "2 studies"


def test_duration__seconds_minutes_hours():
    assert [duration(s) for s in (4.4, 65, 3725)] == ["4 s", "1 min 05 s", "1 h 02 min"]


def test_plain_text__markdown_becomes_what_a_reader_sees():
    assert plain_text("[report](../a/report.html)") == "report"
    assert plain_text(r"a\|b \*c\* `code`") == "a|b *c* code"
    assert plain_text("two\nlines") == "two lines" and plain_text("**best**") == "best"


def test_table_lines__aligned_columns_without_markdown():
    lines = table_lines(("scan", "status"), [("a", "corrected"), ("longer_name", "[x](y)")])
    assert lines == ["scan         status", "-----------  ---------", "a            corrected", "longer_name  x"]
    assert not any("|" in line for line in lines)


def test_print_table__rich_on_a_terminal_plain_in_a_pipe():
    piped, terminal = io.StringIO(), FakeTerminal()
    for stream in (piped, terminal):
        print_table(("scan", "MAE [mm]", "notes"), [("a", "1.0", "a long note " * 20)], stream=stream, clip=("notes",))
    assert piped.getvalue().splitlines()[0].split() == ["scan", "MAE", "[mm]", "notes"]
    assert "┃" in terminal.getvalue() and "MAE [mm]" in terminal.getvalue()  # "[mm]" is text, not markup
    assert "…" in terminal.getvalue() and "|" not in terminal.getvalue()


def test_display__piped_says_start_and_last_and_nothing_between_within_an_interval():
    stream = io.StringIO()
    with Display(stream, every_s=3600) as display, display.step("scans", 50) as advance:
        for i in range(50):
            advance(f"s{i}: corrected")
    lines = stream.getvalue().splitlines()
    assert [line.split(",")[0] for line in lines] == ["scans: 0/50", "scans: 50/50"]
    assert lines[-1].endswith("last s49: corrected")


def test_display__piped_a_slow_step_gets_a_line_per_interval_between_items():
    stream = io.StringIO()
    with Display(stream, every_s=0.1) as display, display.step("trials", 2) as advance:
        advance()
        time.sleep(0.45)  # no trial finishes: the clock says where the step stands
        advance()
    lines = stream.getvalue().splitlines()
    assert lines[0] == "trials: 0/2" and lines[-1].startswith("trials: 2/2")
    assert 1 <= sum(line.startswith("trials: 1/2") for line in lines) <= 6


def test_display__piped_step_without_a_count_says_it_still_runs():
    stream = io.StringIO()
    with Display(stream, every_s=0.05) as display, display.step("training") as now:
        now("round 3")
        time.sleep(0.2)
    lines = stream.getvalue().splitlines()
    assert lines[0] == "training ..." and len(lines) >= 2
    assert all(line.startswith("training: still running (round 3), ") for line in lines[1:])


def test_display__a_step_with_nothing_to_do_prints_nothing():
    stream = io.StringIO()
    with Display(stream) as display, display.step("trials", 0) as advance:
        advance()
    assert stream.getvalue() == ""


def test_display__on_a_terminal_leaves_only_the_echoed_lines():
    stream = FakeTerminal()
    with Display(stream) as display, display.step("trials", 2) as advance:
        display.echo("study 'x': 2 trials run")
        advance()
        advance()
    assert display.live and "study 'x': 2 trials run" in stream.getvalue()


@pytest.mark.parametrize(("args", "fragment"), [
    (["correct", "--frobnicate"], "no such option --frobnicate (mpi-lidar correct --help lists the options)"),
    (["correct", "--mode", "x"], "no such option --mode; did you mean --model? (mpi-lidar correct --help"),
    (["correct", "x", "--out", "o"], "missing option '--model' (mpi-lidar correct --help lists the options)"),
    (["tune", "--data", "d", "--trials", "0"], "mpi-lidar tune --help"),
    (["frobnicate"], "no such command 'frobnicate' (mpi-lidar --help lists the commands)"),
    (["correct", "--model"], "option '--model' requires an argument (mpi-lidar correct --help"),
])
def test_main__a_usage_error_is_one_line(monkeypatch, capsys, args, fragment):
    code, stdout, stderr = call_main(monkeypatch, capsys, *args)
    assert code == 2 and stdout == ""
    assert_one_error_line(stderr, fragment)


def test_main__leaves_the_environment_of_its_caller_as_it_was(monkeypatch, capsys):
    monkeypatch.delenv("PYTHONWARNINGS", raising=False)
    code, _, _ = call_main(monkeypatch, capsys, "correct", "--frobnicate")
    assert code == 2 and "PYTHONWARNINGS" not in os.environ
    monkeypatch.setenv("PYTHONWARNINGS", "error::DeprecationWarning")
    call_main(monkeypatch, capsys, "correct", "--frobnicate")
    assert os.environ["PYTHONWARNINGS"] == "error::DeprecationWarning"


def _outcomes():
    from mpi_lidar.correction import ScanOutcome, ScanStatus

    long_note = "footprint estimate not significant (0.4 sigma): 1,204 pixels left uncalibrated; " * 6
    counts = {"corrected": 10, "no_multipath": 80, "no_return": 10}
    metrics = {"whole map": {"raw_mae_m": 0.0076, "corrected_mae_m": 0.0017}}
    return [
        ScanOutcome("s/a", "corridor_north_wing_2026-11-25_station_0001", ScanStatus.CORRECTED, counts=counts,
                    metrics=metrics, notes=(long_note, "no reference depth")),
        ScanOutcome("s/b", "flat_wall", ScanStatus.UNCHANGED, counts=counts, notes=("no reference depth",)),
        ScanOutcome("s/c", "corner_fp30cm_6m_in_counts", ScanStatus.UNSERVED, counts=counts,
                    reason="amplitude_units: 97 % of the pixels read as saturated; pass --amplitude-scale auto"),
        ScanOutcome("s/d", "dark", ScanStatus.DEGRADED, counts={"no_return": 100}, notes=(long_note,)),
    ]


@pytest.mark.parametrize("width", [80, 120, None])
def test_print_batch__fits_the_width_every_name_and_status_whole_notes_as_codes(width, capsys, monkeypatch):
    from mpi_lidar.cli.correct import print_batch

    monkeypatch.delenv("COLUMNS", raising=False)  # piped (width None): 80 columns
    outcomes = _outcomes()
    print_batch(outcomes, 2.5, "corrected/summary", width)
    lines = capsys.readouterr().out.splitlines()
    assert all(len(line) <= (width or 80) for line in lines), max(lines, key=len)
    assert lines[0] == "4 scans in 2.5 s: 1 corrected, 1 unchanged, 1 degraded, 1 unserved"
    for o in outcomes:
        assert any(line.startswith(o.name) and f" {o.status} " in f"{line} " for line in lines), o.name
    legend = [line for line in lines if line.startswith("n")]
    assert [line.split(":")[0] for line in legend] == ["n1", "n2", "n3"]
    assert "amplitude_units" in lines[lines.index(legend[0]) + 2]
    assert lines[-1].startswith("summary: corrected/summary/report.html")
    header = next(line for line in lines if line.startswith("scan "))
    assert "seconds" not in header and "outputs" not in header and "masked" not in header, "empty columns go"
    assert ("MAE [mm]" in header) == (width == 120)
