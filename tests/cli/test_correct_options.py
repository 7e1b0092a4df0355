"""``mpi-lidar correct``'s options are made from their one declaration, the fields of ``CorrectionOptions`` and
``BatchOptions``: ``--help`` and docs/reference/cli.md say each field's description and real default (the
correction flow's side: tests/flows/test_declared_parameters.py)."""

from __future__ import annotations

import subprocess
import sys

import click
import pytest
from pydantic import BaseModel

from mpi_lidar import cli
from mpi_lidar.correction.options import USER_OPTIONS, CorrectionOptions, UserOption
from mpi_lidar.workflows.batch_options import BATCH_OPTIONS, BatchOptions, batch_options
from tests.test_docs import CLI_PAGE, cli_reference

DECLARED = [(CorrectionOptions, option) for option in USER_OPTIONS] + [(BatchOptions, option)
                                                                       for option in BATCH_OPTIONS]
NAMES = [option.name for _, option in DECLARED]
WIDE = 10_000  # no wrapping: each option's help on one or two lines


def flat(text: str) -> str:
    """Whitespace as single spaces, and a word split at its hyphen by wrapping joined again."""
    return " ".join(text.split()).replace("- ", "-")


def correct_help() -> str:
    command = cli.cli.commands["correct"]
    return command.get_help(click.Context(command, info_name="correct", terminal_width=WIDE, max_content_width=WIDE))


def help_of(text: str, flag: str) -> str:
    """What a ``--help`` text says of ``flag``: its line, and the next where a long option's help begins."""
    lines = text.splitlines()
    start = next(i for i, line in enumerate(lines) if line.strip().startswith(f"{flag} "))
    end = next(i for i in range(start + 1, len(lines)) if lines[i].startswith("  -"))
    return " ".join(lines[start:end])


def said_default(model: type[BaseModel], option: UserOption) -> str | None:
    """The default the help says: the field's (in the option's unit), none for a flag, an empty list or None."""
    default = model.model_fields[option.field].default
    return None if default in (None, False, ()) else option.default_said(model)


@pytest.mark.unit
@pytest.mark.parametrize(("model", "option"), DECLARED, ids=NAMES)
def test_correct_help__each_declared_option_with_its_description_and_default(model, option) -> None:
    said = help_of(correct_help(), option.flag)
    assert flat(option.help_text(model)) in flat(said)
    default = said_default(model, option)
    assert default is None or f"[default: {default}" in said, said


@pytest.mark.unit
def test_correct_help__the_real_defaults() -> None:
    """The defaults the help says are those a scan gets: the amplitude unit is read from the scan (auto)."""
    text, defaults = correct_help(), CorrectionOptions()
    assert "[default: the --sensor profile's, else auto]" in help_of(text, "--amplitude-scale")
    assert "[default: the --sensor profile's, else auto]" in help_of(text, "--footprint-area-m2")
    assert defaults.amplitude_scale == "auto" and defaults.footprint_area_m2 == "auto"
    assert f"[default: {1e3 * defaults.min_multipath_bias_m:g};" in help_of(text, "--min-bias-mm")
    assert f"[default: {defaults.max_invalid_share:g};" in help_of(text, "--max-invalid-share")


@pytest.mark.unit
def test_correct__its_options_are_the_declared_ones_in_order() -> None:
    names = [p.name for p in cli.cli.commands["correct"].params]
    assert names == ["scans", "model_dir", "out_dir", *NAMES]


# A value of each option of a scan, on the command line and in its field's unit.
GIVEN = {"gate": ("all", "all"), "min_bias_mm": ("2.5", 0.0025), "footprint_area_m2": ("0.02", 0.02),
         "amplitude_scale": ("4000", 4000.0), "baseline": ("raw", "raw"), "max_invalid_share": ("0.9", 0.9)}


def parsed(*args: str) -> dict[str, object]:
    """What the correct command's function receives for ``args`` beside a scan, --model and --out."""
    command = cli.cli.commands["correct"]
    with command.make_context("correct", ["a.scan.zarr", "--model", "m", "--out", "o", *args]) as context:
        return context.params


@pytest.mark.unit
@pytest.mark.parametrize("option", USER_OPTIONS, ids=[option.name for option in USER_OPTIONS])
def test_correct__an_option_given_reaches_its_field_in_its_unit(option) -> None:
    text, expected = GIVEN[option.name]
    options, _ = batch_options(parsed(option.flag, text))
    assert getattr(options, option.field) == expected
    assert batch_options(parsed()) == (CorrectionOptions(), BatchOptions()), "nothing given: the defaults"


@pytest.mark.unit
def test_correct__the_batch_options_given_reach_the_batch() -> None:
    _, batch = batch_options(parsed("--fail-on", "degraded", "--fail-on", "unchanged", "--allow-unserved",
                                    "--outputs", "data", "--point-cloud", "ply", "--workers", "3",
                                    "--scheduler", "tcp://host:8786"))
    assert batch == BatchOptions(fail_on=("degraded", "unchanged"), allow_unserved=True, outputs="data",
                                 point_clouds=("ply",), workers=3, scheduler="tcp://host:8786")
    assert batch.point_cloud_formats() == ("ply",) and BatchOptions().point_cloud_formats() is None


def correct_section(page: str) -> list[str]:
    """The correct command's section of the reference, without the line of the help option (click keeps that
    option once made, with -h where the command line has run in this process)."""
    section = page.split("\n## mpi-lidar correct\n", 1)[1].split("\n## ", 1)[0]
    return [line for line in section.splitlines() if "Show this message and exit." not in line]


@pytest.mark.unit
def test_cli_reference__up_to_date_and_says_each_declared_option() -> None:
    ours = correct_section(CLI_PAGE.read_text())
    assert ours == correct_section(cli_reference()), "regenerate it: .venv/bin/python -m tests.test_docs"
    for model, option in DECLARED:
        assert flat(option.help_text(model)) in flat("\n".join(ours)), option.name


@pytest.mark.integration
def test_import_cli__builds_no_declared_option() -> None:
    """``mpi-lidar --help`` lists the commands without importing the options' models (numpy, the correction)."""
    code = ("import sys\nimport mpi_lidar.cli\nprint(sorted(m for m in ('numpy', 'mpi_lidar.correction.options', "
            "'mpi_lidar.workflows.batch_options') if m in sys.modules))")
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert done.stdout.strip() == "[]"
