"""Command line: ``mpi-lidar COMMAND``, one module per command. A user error is one line on stderr, exit 2.

Start-up stays quick: a command imports what its work needs inside its function, and the options declared by
the library's models are built when that command's options are first asked for (:mod:`mpi_lidar.cli._declared`).
"""

from __future__ import annotations

import errno
import os
import sys
import traceback
from pathlib import Path

import click

from mpi_lidar.cli import (
    bench,
    calibrate,
    correct,
    evaluate,
    import_scan,
    pipeline,
    render_scenes,
    simulate,
    table2,
    train,
    tune,
    verify,
)
from mpi_lidar.cli._common import feature_spec
from mpi_lidar.errors import EXIT_FAILURE, EXIT_USER_ERROR, MpiLidarError, environment_fault, write_error_log
from mpi_lidar.redact import install_log_redaction, redact

__all__ = ["EXIT_USER_ERROR", "cli", "feature_spec", "main"]


@click.group(context_settings={"help_option_names": ["-h", "--help"]})
@click.version_option(package_name="mpi-lidar")
@click.option("--debug", is_flag=True, expose_value=False,
              help="Print the traceback of an unexpected error (it is always written to a log file).")
def cli() -> None:
    """Multipath-interference suppression for AMCW coaxial scanning LiDAR."""


for _command in (simulate.simulate, tune.tune, train.train, evaluate.evaluate, pipeline.pipeline, correct.correct,
                 calibrate.calibrate, import_scan.import_scan, render_scenes.render_scenes, table2.table2,
                 bench.bench, verify.verify):
    cli.add_command(_command)


def main() -> None:
    """Run the command line; every error is one line on stderr.

    A user error (bad input, a damaged store, an unreachable service, a mistyped option) exits 2; anything
    unexpected exits 1 with its traceback written to a log file (printed with ``--debug``). Secrets are masked in
    every line. Without ``--debug`` nothing else reaches stderr (:func:`_quiet`).
    """
    install_log_redaction()  # every log line of every library, masked as the error lines are
    debug = "--debug" in sys.argv[1:]
    if debug:
        sys.argv.remove("--debug")
    inherited = os.environ.get("PYTHONWARNINGS")
    try:
        if not debug:
            _quiet()
        _run(debug)
    finally:  # this process's environment as it was (the command line called from Python, as in tests)
        if inherited is None:
            os.environ.pop("PYTHONWARNINGS", None)
        else:
            os.environ["PYTHONWARNINGS"] = inherited


def _run(debug: bool) -> None:
    """The command of ``sys.argv``; every error one line on stderr and its exit code (:func:`main`)."""
    try:
        cli.main(standalone_mode=False, prog_name="mpi-lidar")
    except click.ClickException as exc:
        click.echo(f"error: {redact(_usage_line(exc))}", err=True)
        sys.exit(EXIT_USER_ERROR)
    except (click.Abort, KeyboardInterrupt):
        click.echo("aborted", err=True)
        sys.exit(130)
    except MpiLidarError as exc:
        click.echo(f"error: {redact(str(exc))}", err=True)
        if debug:
            traceback.print_exc()
        sys.exit(EXIT_USER_ERROR)
    except Exception as exc:  # a bug or an environment problem: one line, the traceback in a file
        # a full disk, a quota, a read-only file system, a path too long: the user's to fix
        fault = environment_fault(exc) or path_fault(exc)
        if fault is not None:
            click.echo(f"error: {redact(str(fault))}", err=True)
            if debug:
                click.echo(redact(traceback.format_exc()), err=True)
            sys.exit(EXIT_USER_ERROR)
        log = _write_traceback()
        reason = redact(str(exc).strip().splitlines()[0]) if str(exc).strip() else ""
        click.echo(f"error: unexpected {type(exc).__name__}: {reason} (traceback in {log}; rerun with --debug "
                   "to print it)", err=True)
        if debug:
            click.echo(redact(traceback.format_exc()), err=True)
        sys.exit(EXIT_FAILURE)


# How much of an absurd path an error line shows at either end [characters].
SHOWN_PATH_END = 48


def shortened(path: str) -> str:
    """A path as an error line shows it: whole if short, else its start and end around an ellipsis."""
    return path if len(path) <= 2 * SHOWN_PATH_END + 3 else f"{path[:SHOWN_PATH_END]}...{path[-SHOWN_PATH_END:]}"


def path_fault(exc: BaseException) -> MpiLidarError | None:
    """A path the file system refuses as too long (``ENAMETOOLONG``) as the user's error, the path shortened;
    None for any other exception."""
    if not isinstance(exc, OSError) or exc.errno != errno.ENAMETOOLONG:
        return None
    name = exc.filename if isinstance(exc.filename, str) else os.fsdecode(exc.filename or b"")
    where = f" ({len(name):,} characters: {shortened(name)})" if name else ""
    return MpiLidarError(f"a path is too long for the file system{where}; give a shorter path (each name at most "
                         "255 bytes, the whole path at most 4,096)")


def _usage_line(exc: click.ClickException) -> str:
    """A usage error as one line: what is wrong and which ``--help`` lists the choices (Click's own message is
    three lines: usage, a hint and the error)."""
    if isinstance(exc, click.NoSuchOption):
        message = f"no such option {exc.option_name}"
        if exc.possibilities:
            message += f"; did you mean {' or '.join(sorted(exc.possibilities))}?"
    else:
        message = " ".join(exc.format_message().split())
        message = message[:1].lower() + message[1:]
    if not isinstance(exc, click.UsageError):
        return message
    ctx = exc.ctx
    if ctx is not None and not isinstance(ctx.command, click.Group):
        where = f"{ctx.command_path} --help lists the options"
    else:  # the group's own error (a mistyped command), or one raised before a command's context existed
        command = next((arg for arg in sys.argv[1:] if arg in cli.commands), None)
        where = (f"mpi-lidar {command} --help lists the options" if command and ctx is None
                 else "mpi-lidar --help lists the commands")
    return message.rstrip(".") + f" ({where})"


def _quiet() -> None:
    """Keep stderr for error lines, in this process and in the Dask worker processes it starts.

    numpy's RuntimeWarnings (an infinite depth, an overflow in a pixel's arithmetic) concern pixels that the
    validity stage flags and leaves out; they say nothing a user can act on. asyncio's and tornado's ERROR lines
    ("Task was destroyed but it is pending!") come from Dask's event loop being torn down after an error that
    has been reported already. Errors themselves are never silenced: they are exceptions, and each becomes one
    ``error:`` line. ``--debug`` shows everything.
    """
    import logging
    import warnings

    warnings.filterwarnings("ignore", category=RuntimeWarning)
    inherited = os.environ.get("PYTHONWARNINGS")  # for the worker processes this command starts
    os.environ["PYTHONWARNINGS"] = ",".join(filter(None, (inherited, "ignore::RuntimeWarning")))
    for name in ("asyncio", "tornado"):
        logging.getLogger(name).setLevel(logging.CRITICAL)


def _write_traceback() -> Path | str:
    """The current exception's traceback, secrets masked, in this user's private log file; its path."""
    return write_error_log(redact(traceback.format_exc())) or "no log: the temporary folder cannot be written"

