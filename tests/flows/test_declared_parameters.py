"""The correction flow's parameters are the declared options of ``mpi-lidar correct`` (the fields of
``CorrectionOptions`` and ``BatchOptions``): the same names and defaults, each described in the flow's parameter
schema and in ``python -m flows correct-archive --help`` by its field's description, and refused, when bad, with
one ``error:`` line before a flow run starts (the command line's side: tests/cli/test_correct_options.py).
"""

from __future__ import annotations

import inspect
import os

import pytest
from prefect import get_client
from prefect.client.schemas.filters import FlowFilter, FlowFilterName

import flows.__main__ as runner
from flows.correct import correct_archive_flow
from mpi_lidar import cli
from mpi_lidar.correction.options import USER_OPTIONS, CorrectionOptions
from mpi_lidar.workflows.batch_options import BATCH_OPTIONS, BatchOptions

DECLARED = [(CorrectionOptions, option) for option in USER_OPTIONS] + [(BatchOptions, option)
                                                                       for option in BATCH_OPTIONS]
NAMES = [option.name for _, option in DECLARED]


def flat(text: str) -> str:
    return " ".join(text.split())


def test_correction_flow__a_parameter_per_declared_option_with_the_commands_default() -> None:
    parameters = inspect.signature(correct_archive_flow.fn).parameters
    assert list(parameters) == ["scans", "model", "out", *NAMES]
    command = cli.cli.commands["correct"]
    with command.make_context("correct", ["a.scan.zarr", "--model", "m", "--out", "o"]) as context:
        theirs = {name: None if value == () else value for name, value in context.params.items()}
    assert {name: parameters[name].default for name in NAMES} == {name: theirs[name] for name in NAMES}


@pytest.mark.parametrize(("model", "option"), DECLARED, ids=NAMES)
def test_correction_flow__schema_and_help_describe_each_declared_option(model, option) -> None:
    described = correct_archive_flow.parameters.properties[option.name]["description"]
    assert flat(described).startswith(flat(option.help_text(model)))
    parser = runner.build_parser("correct-archive", correct_archive_flow)
    action = next(a for a in parser._actions if a.dest == option.name)
    assert flat(option.help_text(model)) in flat(action.help or "")


def schema_values(name: str) -> list[str]:
    """The values the flow's parameter schema allows for ``name`` (or each item of it), references resolved."""
    schema = correct_archive_flow.parameters
    found = schema.properties[name]
    found = found["anyOf"][0]["items"] if "anyOf" in found else found  # a list, or None
    return schema.definitions[found["$ref"].rsplit("/", 1)[-1]]["enum"] if "$ref" in found else found["enum"]


def test_correction_flow__enum_parameters_list_the_enums_values() -> None:
    values = schema_values
    assert values("gate") == ["geometry", "all", "consistency"] and values("baseline") == ["fused", "raw"]
    assert values("outputs") == ["full", "light", "data"] and values("point_clouds") == ["las", "laz", "ply"]
    assert values("fail_on") == ["degraded", "unchanged", "failed"]


@pytest.mark.parametrize("bad", [["--min-bias-mm", "-1"], ["--amplitude-scale", "0"], ["--workers", "-1"],
                                 ["--max-invalid-share", "2"]])
def test_main__a_bad_option_is_one_error_line_and_no_flow_run(bad, tmp_path, monkeypatch, capsys) -> None:
    for name, value in runner.QUIET_ENVIRONMENT.items():  # main sets them where unset: keep them in this test
        monkeypatch.setenv(name, os.environ.get(name, value))
    before = flow_runs("correct-archive")
    out = tmp_path / "corrected"
    code = runner.main(["correct-archive", "--scans", str(tmp_path / "a.scan.zarr"), "--model", str(tmp_path / "m"),
                        "--out", str(out), *bad])
    captured = capsys.readouterr()
    assert code == 2 and captured.out == ""
    assert len(captured.err.splitlines()) == 1 and captured.err.startswith("error: "), captured.err
    assert flow_runs("correct-archive") == before and not out.exists()


def flow_runs(name: str) -> int:
    with get_client(sync_client=True) as client:
        return len(client.read_flow_runs(flow_filter=FlowFilter(name=FlowFilterName(any_=[name]))))
