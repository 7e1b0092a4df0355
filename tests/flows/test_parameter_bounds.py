"""``python -m flows``: a parameter past its declared bound is one ``error:`` line and exit 2 before a flow run
starts, as the command line's option is (tests/cli/test_option_bounds.py). In this process: the parse and the
checks run before any flow, so no run, no JSON and no Prefect line may appear."""

from __future__ import annotations

import inspect
import os
import typing

import pytest

import flows.__main__ as runner
from mpi_lidar.correction.options import USER_OPTIONS
from mpi_lidar.workflows.batch_options import BATCH_OPTIONS
from tests.cli_runner import assert_one_error_line

CORRECT = ["correct-archive", "--scans", "a.scan.zarr", "--model", "m", "--out", "o"]
# One bad value per flow and bounded parameter: (flow and its required parameters, the option, the bad value).
BAD_VALUES = [
    (["generate-dataset", "--out", "d.zarr"], "--workers", "-1"),
    (["generate-dataset", "--out", "d.zarr"], "--samples", "-5"),
    (["generate-dataset", "--out", "d.zarr"], "--chunk-rows", "0"),
    (["generate-dataset", "--out", "d.zarr"], "--seed", "-1"),
    (["regenerate-dataset", "--root", "r"], "--workers", "-1"),
    (["tune", "--data", "d.zarr"], "--trials", "0"),
    (["tune", "--data", "d.zarr"], "--tune-rows", "99"),
    (["tune", "--data", "d.zarr"], "--workers", "-1"),
    (["train", "--data", "d.zarr", "--out", "m"], "--workers", "-1"),
    (["table-2", "--data", "d.zarr", "--report", "r"], "--trials", "0"),
    (["table-2", "--data", "d.zarr", "--report", "r"], "--train-rows", "9"),
    (["table-2", "--data", "d.zarr", "--report", "r"], "--svm-rows", "-1"),
    (["pipeline"], "--trials", "-5"),
    (["pipeline"], "--tune-rows", "1"),
    (["pipeline"], "--workers", "-1"),
    (CORRECT, "--min-bias-mm", "-1"),
    (CORRECT, "--amplitude-scale", "0"),
    (CORRECT, "--footprint-area-m2", "1e9"),
    (CORRECT, "--max-invalid-share", "1.5"),
    (CORRECT, "--no-return-range", "0"),
    (CORRECT, "--workers", "-1"),
]


@pytest.fixture
def quiet(monkeypatch: pytest.MonkeyPatch) -> None:
    for name, value in runner.QUIET_ENVIRONMENT.items():  # main sets them where unset: keep them in this test
        monkeypatch.setenv(name, os.environ.get(name, value))


def run_main(args: list[str]) -> int:
    try:
        return runner.main(args)
    except SystemExit as exc:  # argparse's refusal
        return int(exc.code or 0)


@pytest.mark.slow
@pytest.mark.parametrize(("flow", "option", "value"), BAD_VALUES, ids=[f"{f[0]} {o} {v}" for f, o, v in BAD_VALUES])
def test_main__a_value_past_its_bound_is_one_line_exit_2_before_a_flow_run(quiet, capsys: pytest.CaptureFixture[str],
                                                                          flow, option, value) -> None:
    code = run_main([*flow, option, value])
    captured = capsys.readouterr()
    assert code == 2
    assert_one_error_line(captured.err)
    name = option.removeprefix("--").replace("-", "_")
    field = next((o.field for o in (*USER_OPTIONS, *BATCH_OPTIONS) if o.name == name), name)  # as the model says
    assert any(said in captured.err for said in (option, name, field)), captured.err
    assert captured.out == ""  # a flow run prints its JSON result on stdout
    assert "flow run" not in captured.err.lower() and "Finished in state" not in captured.err


def _bounded_parameters() -> set[tuple[str, str]]:
    """(flow, option) of every flow parameter annotated with bounds."""
    found = set()
    for name in runner.FLOWS:
        fn = runner.load_flow(name).fn
        hints = typing.get_type_hints(fn, include_extras=True)
        for parameter in inspect.signature(fn).parameters:
            if typing.get_origin(runner._without_none(hints[parameter])) is typing.Annotated:
                found.add((name, f"--{parameter.replace('_', '-')}"))
    return found


def test_bad_values__every_bounded_flow_parameter_is_probed() -> None:
    probed = {(flow[0], option) for flow, option, _ in BAD_VALUES}
    assert _bounded_parameters() and _bounded_parameters() - probed == set()


def test_main__a_path_past_the_file_systems_limits_is_one_short_line_before_a_flow_run(
        quiet, capsys: pytest.CaptureFixture[str]) -> None:
    long = "/tmp/" + "/".join(["d" * 200] * 25) + "/x.zarr"  # 5,036 characters
    for args in (["generate-dataset", "--out", long], ["evaluate", "--data", long, "--model", "m", "--report", "r"],
                 ["correct-archive", "--scans", "a.scan.zarr", "/tmp/" + "s" * 300, "--model", "m", "--out", "o"]):
        assert run_main(args) == 2
        captured = capsys.readouterr()
        assert_one_error_line(captured.err, "a path is too long for the file system")
        assert len(captured.err) < 400 and captured.out == ""


def test_failure_line__a_path_too_long_inside_a_run_is_said_shortened() -> None:
    import errno

    from prefect.states import Failed

    state = Failed(data=OSError(errno.ENAMETOOLONG, "File name too long", "/x" * 3000))
    line = runner.failure_line(state)
    assert line.startswith("a path is too long for the file system (6,000 characters") and len(line) < 300
