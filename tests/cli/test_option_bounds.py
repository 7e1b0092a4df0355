"""Every numeric option with a physical bound is declared once with it (mpi_lidar/workflows/job_options.py, the
dataset configuration, the correction's options): a value past it is one ``error:`` line and exit 2 before the
command does anything (the flows' side: tests/flows/test_parameter_bounds.py)."""

from __future__ import annotations

import typing

import click
import pytest

from mpi_lidar import cli
from mpi_lidar.cli._declared import bounded
from mpi_lidar.config import DatasetConfig
from mpi_lidar.workflows import job_options
from tests.cli_runner import assert_one_error_line, call_main

# One bad value per command and bounded option: (command and its required options, the option, the bad value).
BAD_VALUES = [
    (["simulate", "--out", "{out}"], "--samples", "0"),
    (["simulate", "--out", "{out}"], "--chunk-rows", "-1"),
    (["simulate", "--out", "{out}"], "--seed", "-1"),
    (["simulate", "--out", "{out}"], "--workers", "-1"),
    (["tune", "--data", "d.zarr"], "--trials", "0"),
    (["tune", "--data", "d.zarr"], "--tune-rows", "99"),
    (["tune", "--data", "d.zarr"], "--workers", "-1"),
    (["train", "--data", "d.zarr", "--out", "{out}"], "--workers", "-2"),
    (["pipeline", "--out", "{out}"], "--trials", "-5"),
    (["pipeline", "--out", "{out}"], "--tune-rows", "1"),
    (["pipeline", "--out", "{out}"], "--workers", "-1"),
    (["table2", "--data", "d.zarr", "--out", "{out}"], "--svm-rows", "9"),
    (["table2", "--data", "d.zarr", "--out", "{out}"], "--train-rows", "0"),
    (["table2", "--data", "d.zarr", "--out", "{out}"], "--trials", "0"),
    (["bench", "--out", "{out}"], "--rows", "5"),
    (["bench", "--out", "{out}"], "--seed", "-3"),
    (["render-scenes", "--out", "{out}"], "--seed", "-1"),
    (["correct", "a.scan.zarr", "--model", "m", "--out", "{out}"], "--max-invalid-share", "1.5"),
    (["correct", "a.scan.zarr", "--model", "m", "--out", "{out}"], "--min-bias-mm", "-1"),
    (["correct", "a.scan.zarr", "--model", "m", "--out", "{out}"], "--workers", "-1"),
    (["correct", "a.scan.zarr", "--model", "m", "--out", "{out}"], "--no-return-range", "0"),
]


@pytest.mark.unit
@pytest.mark.parametrize(("command", "option", "value"), BAD_VALUES,
                         ids=[f"{c[0]} {o} {v}" for c, o, v in BAD_VALUES])
def test_command__a_value_past_its_bound_is_one_line_exit_2_and_nothing_written(tmp_path, monkeypatch, capsys,
                                                                                command, option, value):
    out = tmp_path / "out"
    args = [arg.format(out=out) for arg in command]
    code, stdout, stderr = call_main(monkeypatch, capsys, *args, option, value)
    assert code == 2
    assert_one_error_line(stderr, f"invalid value for '{option}'")
    assert value in stderr and stdout == ""
    assert not out.exists()


def _bounded_options() -> list[tuple[str, str]]:
    """(command, option) of every option of a number with a declared lower or upper bound."""
    found = []
    for name, command in cli.cli.commands.items():
        ctx = click.Context(command, info_name=name)
        for param in command.get_params(ctx):
            if isinstance(param.type, click.IntRange | click.FloatRange):
                found.append((name, param.opts[0]))
    return found


@pytest.mark.unit
def test_bad_values__every_bounded_option_of_every_command_is_probed():
    probed = {(command[0], option) for command, option, _ in BAD_VALUES}
    assert set(_bounded_options()) - probed == set()


@pytest.mark.unit
@pytest.mark.parametrize("name", ["Seed", "Workers", "Trials", "TuneRows", "BaselineRows"])
def test_bounded__click_range_is_the_declarations(name):
    declared = getattr(job_options, name)
    low = next(meta.ge for meta in typing.get_args(declared)[1].metadata if hasattr(meta, "ge"))
    kind = bounded(declared)
    assert isinstance(kind, click.IntRange) and kind.min == low and not kind.min_open
    with pytest.raises(click.BadParameter):
        kind.convert(low - 1, None, None)
    assert kind.convert(low, None, None) == low


@pytest.mark.unit
def test_bounded__a_models_field_keeps_its_upper_bound():
    kind = bounded(DatasetConfig.model_fields["chunk_rows"])
    assert (kind.min, kind.max) == (1, 10_000_000)
