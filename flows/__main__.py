"""Run one flow in this process, on its embedded defaults: ``python -m flows <flow> [--<parameter> VALUE]...``.

Every parameter of the flow is an option, spelled as the parameter with dashes (``min_bias_mm`` is
``--min-bias-mm``); a list takes one or more values and may be repeated (``--scans a b --scans c``), a
boolean is ``--name`` / ``--no-name``. The options are read from the flow's own signature and its parameter
schema, so they, their choices, defaults and help are the flow's, which are ``mpi-lidar``'s
(:data:`CLI_SPELLINGS` adds the CLI's spelling where a parameter is named otherwise). A flow of
:data:`CHECKS` has its parameters checked as the command line checks its options before the flow runs. At the
end the flow run's id, final state and result are printed as one JSON object on stdout; a flow run that fails
prints it too (its ``result`` what the failure carries, e.g. the statuses of a batch's scans, else null, and its
``error``), then one ``error:`` line on stderr (:func:`failure_line`), and exits 1; an unknown flow, an unknown
option, a bad choice or a value out of its bounds prints one ``error:`` line and exits 2, before any flow run starts.

Without ``PREFECT_API_URL`` the run reports to a temporary Prefect server of its own, started while the
flow's modules import. The console shows warnings and errors only (the flow and task runs' INFO lines still
reach the API); ``PREFECT_LOGGING_HANDLERS_CONSOLE_LEVEL=INFO`` shows them, and an error's traceback only
with ``--debug``. Nothing reports usage to Prefect's public endpoint (see :mod:`flows`).
"""

from __future__ import annotations

import argparse
import contextlib
import enum
import errno
import importlib
import inspect
import json
import logging
import os
import sys
import types
import typing
from collections.abc import Callable, Sequence
from concurrent.futures import Future, ThreadPoolExecutor
from concurrent.futures import wait as wait_all
from typing import Any

# Quiet console for a run from the terminal, set before anything imports Prefect or Dask (their worker processes
# inherit it); the environment wins where it says otherwise.
QUIET_ENVIRONMENT = {
    "PREFECT_LOGGING_HANDLERS_CONSOLE_LEVEL": "WARNING",  # flow and task runs still log INFO to the API
    "DASK_LOGGING__DISTRIBUTED": "error",  # the LocalCluster's start, stop and worker-restart chatter
    # The temporary server's first start in a new PREFECT_HOME creates its database: on a busy machine that
    # takes longer than Prefect's 20 s, and a second server would then be started on the same port.
    "PREFECT_SERVER_EPHEMERAL_STARTUP_TIMEOUT_SECONDS": "120",
}

# Each flow under its Prefect name (as in deployments: 'tune/tune'): module and attribute.
FLOWS = {
    "generate-dataset": "flows.generate_dataset:generate_dataset_flow",
    "regenerate-dataset": "flows.regenerate:regenerate_dataset_flow",
    "tune": "flows.tune:tune_flow",
    "train": "flows.train:train_flow",
    "evaluate": "flows.evaluate:evaluate_flow",
    "table-2": "flows.evaluate:table2_flow",
    "correct-archive": "flows.correct:correct_archive_flow",
    "pipeline": "flows.pipeline:pipeline_flow",
}
SUMMARIES = {
    "generate-dataset": "generate (or resume) a labelled dataset store, as mpi-lidar simulate",
    "regenerate-dataset": "the dataset of this configuration and code version under a root, as scheduled nightly",
    "tune": "the Optuna study, as mpi-lidar tune",
    "train": "the final model, as mpi-lidar train",
    "evaluate": "test-split metrics and report, as mpi-lidar evaluate",
    "table-2": "the paper's Table II with its baselines, as mpi-lidar table2",
    "correct-archive": "batch correction of scans, as mpi-lidar correct",
    "pipeline": "the main job, as mpi-lidar pipeline",
}
# The command line's other spellings of a flow parameter: mpi-lidar correct --point-cloud, evaluate --out.
CLI_SPELLINGS = {"point_clouds": ["--point-cloud"], "report": ["--out"]}
# What checks a flow's parameters, as the command line checks its options, before a run starts: a callable
# that takes the parameters by name and raises MpiLidarError for a bad one.
CHECKS: dict[str, str | Callable[[dict[str, object]], object]] = {
    "correct-archive": "mpi_lidar.workflows.batch_options:batch_options",
}


# The parameters that name files or directories (or globs, or URLs): one past the file system's limits is refused
# before a run starts, as the command line refuses it, the path shortened (:func:`mpi_lidar.cli.path_fault`).
PATH_PARAMETERS = ("out", "data", "model", "report", "report_dir", "root", "scans", "config_file", "sensor")
NAME_MAX_BYTES, PATH_MAX_BYTES = 255, 4096


def check_path_lengths(args: dict[str, object]) -> None:
    """Refuse a local path among :data:`PATH_PARAMETERS` longer than the file system takes (a name past
    :data:`NAME_MAX_BYTES`, the whole past :data:`PATH_MAX_BYTES`) with one line: MpiLidarError."""
    from mpi_lidar.cli import path_fault

    for name in PATH_PARAMETERS:
        given = args.get(name)
        for value in given if isinstance(given, list) else [given]:
            if not isinstance(value, str) or "://" in value:
                continue
            encoded = os.fsencode(value)
            if len(encoded) >= PATH_MAX_BYTES or any(len(part) > NAME_MAX_BYTES for part in encoded.split(b"/")):
                fault = path_fault(OSError(errno.ENAMETOOLONG, os.strerror(errno.ENAMETOOLONG), value))
                assert fault is not None  # an ENAMETOOLONG always has one
                raise fault


def check_configuration(args: dict[str, object]) -> object:
    """The configuration a dataset flow's preset, file and options make (and its sensor profile's), checked as
    ``mpi-lidar simulate`` checks them: MpiLidarError with one line for a bad one."""
    from mpi_lidar.calibration.profile import read_profile
    from mpi_lidar.config import resolve_config, validate_overrides

    given = {key: args.get(key) for key in ("samples", "chunk_rows", "seed", "fidelity") if key in args}
    config_file = args.get("config_file")
    config = resolve_config(str(config_file) if config_file else None, str(args.get("preset") or "quick"),
                            **given)  # type: ignore[arg-type]
    sensor = args.get("sensor")
    if sensor:
        config = validate_overrides(read_profile(str(sensor)).simulation(), config, source=f"sensor profile {sensor}")
    return config


CHECKS.update({"generate-dataset": check_configuration, "regenerate-dataset": check_configuration})


class OneLineParser(argparse.ArgumentParser):
    """argparse, whose errors are one ``error:`` line naming the ``--help`` that lists the options (exit 2)."""

    def error(self, message: str) -> typing.NoReturn:
        print(f"error: {message} ({self.prog} --help lists the options)", file=sys.stderr)
        raise SystemExit(2)


def quiet_environment() -> None:
    """Set :data:`QUIET_ENVIRONMENT` where the environment does not set it already."""
    for name, value in QUIET_ENVIRONMENT.items():
        os.environ.setdefault(name, value)


def load_flow(name: str) -> Any:
    return _load(FLOWS[name])


def _load(where: str) -> Any:
    module, attribute = where.split(":")
    return getattr(importlib.import_module(module), attribute)


def _plain(value: object) -> object:
    """A default as the command line gives it: an enum member as its value."""
    return value.value if isinstance(value, enum.Enum) else value


def _without_none(annotation: Any) -> Any:
    """The annotation without ``None`` (``str | None`` is ``str``): a missing option is the default."""
    if isinstance(annotation, types.UnionType) or typing.get_origin(annotation) is typing.Union:
        args = [a for a in typing.get_args(annotation) if a is not type(None)]
        return args[0] if len(args) == 1 else typing.Union[tuple(args)]  # noqa: UP007 (built at run time)
    return annotation


def _choices(annotation: Any) -> list[str] | None:
    """The values the annotation allows, as its JSON schema lists them (a ``Literal``, an enum); None: any."""
    from pydantic import TypeAdapter

    if annotation in (int, float, str):
        return None
    try:
        listed = TypeAdapter(annotation).json_schema().get("enum")
    except Exception:  # a type without a JSON schema takes any text
        return None
    return None if listed is None else [str(v) for v in listed]


def _converter(annotation: Any) -> tuple[Callable[[str], object], list[str] | None]:
    """How one value of the annotation is read from text, and its choices (a ``Literal``'s or an enum's); a
    number declared with bounds (``Annotated[int, Field(ge=1)]``, :mod:`mpi_lidar.workflows.job_options`) is
    refused past them as the command line refuses it."""
    if typing.get_origin(annotation) is typing.Annotated:
        return _bounded_reader(annotation), None
    choices = _choices(annotation)
    if choices is not None:
        return str, choices
    members = typing.get_args(annotation) if typing.get_origin(annotation) in (typing.Union, types.UnionType) else ()
    if members:  # e.g. float | str: footprint_area_m2 is a number or "auto"
        readers = [_converter(m)[0] for m in members]

        def number_or_text(text: str) -> object:
            for read in readers:
                try:
                    return read(text)
                except ValueError:
                    continue
            raise ValueError(text)
        return number_or_text, None
    if annotation in (int, float, str):
        return annotation, None
    raise TypeError(f"no command-line reading for {annotation!r}")


def _bounded_reader(annotation: Any) -> Callable[[str], object]:
    """A reader of the annotation's type that refuses a value past its declared bounds (argparse's one line)."""
    from pydantic import TypeAdapter, ValidationError

    read, _ = _converter(typing.get_args(annotation)[0])
    adapter = TypeAdapter(annotation)

    def bounded(text: str) -> object:
        value = read(text)
        try:
            return adapter.validate_python(value)
        except ValidationError as exc:
            message = exc.errors(include_url=False)[0]["msg"]
            raise argparse.ArgumentTypeError(f"{text}: {message[:1].lower()}{message[1:]}") from None
    bounded.__name__ = getattr(read, "__name__", "number")  # argparse names it where text is no number at all
    return bounded


def _bounds_said(annotation: Any) -> str:
    """A bounded number's bounds as help says them ("; at least 1"), else nothing."""
    from pydantic import TypeAdapter

    if typing.get_origin(annotation) is not typing.Annotated:
        return ""
    schema = TypeAdapter(annotation).json_schema()
    words = {"minimum": "at least", "exclusiveMinimum": "above", "maximum": "at most", "exclusiveMaximum": "below"}
    said = [f"{word} {schema[key]:,}" if isinstance(schema[key], int) else f"{word} {schema[key]:g}"
            for key, word in words.items() if key in schema]
    return "; " + ", ".join(said) if said else ""


def build_parser(name: str, flow: Any) -> argparse.ArgumentParser:
    """An option per parameter of ``flow``, with its type, choices and default read from its signature and its
    help from the flow's parameter schema (the ``Args:`` section of its docstring)."""
    from flows.parameters import description

    fn = flow.fn
    parser = OneLineParser(prog=f"python -m flows {name}",
                                     description=description(inspect.getdoc(fn)) or SUMMARIES[name],
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    hints = typing.get_type_hints(fn, include_extras=True)  # Annotated kept: its schema may narrow the choices
    helps = {key: schema.get("description") for key, schema in flow.parameters.properties.items()}
    for parameter in inspect.signature(fn).parameters.values():
        annotation = _without_none(hints[parameter.name])
        flags = [f"--{parameter.name.replace('_', '-')}", *CLI_SPELLINGS.get(parameter.name, [])]
        required = parameter.default is inspect.Parameter.empty
        default = None if required else _plain(parameter.default)
        listed = typing.get_origin(annotation) is list
        said = (("required" if required else f"default: {default}") + _bounds_said(annotation)
                + ("; one or more, repeatable" if listed else ""))
        shown = f"{helps[parameter.name]} ({said})" if helps.get(parameter.name) else said
        if annotation is bool:
            parser.add_argument(*flags, dest=parameter.name, action=argparse.BooleanOptionalAction,
                                default=default, required=required, help=shown)
            continue
        if listed:
            read, choices = _converter(typing.get_args(annotation)[0])
            parser.add_argument(*flags, dest=parameter.name, type=read, choices=choices, nargs="+",
                                action="extend", default=None, required=required,
                                help=shown)
            continue
        read, choices = _converter(annotation)
        parser.add_argument(*flags, dest=parameter.name, type=read, choices=choices, default=default,
                            required=required, help=shown)
    parser.add_argument("--debug", action="store_true", help="show the traceback of an error")
    return parser


class _WithoutTraceback(logging.Filter):
    """Leaves a record's traceback out of the console: the run ends with its one ``error:`` line."""

    def filter(self, record: logging.LogRecord) -> bool:
        record.exc_info, record.exc_text, record.stack_info = None, None, None
        return True


def console_without_tracebacks() -> None:
    """Prefect's console handler (set up when the flow's modules imported Prefect) prints no tracebacks.

    The API handlers of the flow and task runs see the records first, so the runs' logs keep them.
    """
    from prefect.logging.handlers import PrefectConsoleHandler

    for handler in logging.getLogger().handlers:
        if isinstance(handler, PrefectConsoleHandler):
            handler.addFilter(_WithoutTraceback())


def start_api_in_background() -> Future[None] | None:
    """Start this process's temporary Prefect server while the flow's modules import (no URL set: none).

    :func:`flows.runtime.api_url` finds it afterwards, as ``prefect.get_client()`` does: it is the process's
    default instance. The caller waits for the future (which raises what the start raised) before any flow runs.
    """
    from prefect.settings import get_current_settings

    if get_current_settings().api.url:
        return None
    from prefect.server.api.server import SubprocessASGIServer

    pool = ThreadPoolExecutor(1, thread_name_prefix="start-prefect-server")
    started = pool.submit(SubprocessASGIServer().start)
    pool.shutdown(wait=False)  # the start goes on; the future tells when it is done
    return started


def stop_api() -> None:
    from prefect.server.api.server import SubprocessASGIServer

    SubprocessASGIServer().stop()


def failure_line(state: Any) -> str:
    """Why a flow run failed, in one line: a user error's own message (as ``mpi-lidar`` prints it), else the
    exception's type and message, else the state's message."""
    from mpi_lidar.cli import path_fault
    from mpi_lidar.errors import MpiLidarError, environment_fault

    try:
        raised = state.result(raise_on_failure=False)
    except Exception:  # the result cannot be read back: the state's message says enough
        raised = None
    if isinstance(raised, MpiLidarError):
        return str(raised)
    fault = environment_fault(raised) or path_fault(raised) if isinstance(raised, BaseException) else None
    if fault is not None:  # a full disk, a path too long: the user's to fix, said as the command line says it
        return str(fault)
    if isinstance(raised, BaseException):
        return f"{type(raised).__name__}: {raised}"
    return state.message or state.name


def carried_result(state: Any) -> object:
    """What a failed flow run's error carries as its result (its ``result`` attribute: the correction flow's
    statuses of the scans that were corrected), else None."""
    try:
        raised = state.result(raise_on_failure=False)
    except Exception:  # the result cannot be read back
        return None
    return getattr(raised, "result", None) if isinstance(raised, BaseException) else None


def _usage() -> str:
    width = max(map(len, FLOWS))
    lines = [f"  {name:<{width}}  {SUMMARIES[name]}" for name in FLOWS]
    return ("usage: python -m flows FLOW [--PARAMETER VALUE]...\n\nflows (python -m flows FLOW --help for its "
            "options):\n" + "\n".join(lines))


def _refused(name: str, args: dict[str, object]) -> str | None:
    """Why the flow's parameters are refused (:data:`CHECKS`), before a run starts; None if they are not."""
    from mpi_lidar.errors import MpiLidarError
    from mpi_lidar.redact import redact

    check = CHECKS.get(name)
    try:
        check_path_lengths(args)
        if check is not None:
            (check if callable(check) else _load(check))(args)
    except MpiLidarError as exc:
        return redact(str(exc))
    return None


def main(argv: Sequence[str] | None = None) -> int:
    """Parse, run the flow in this process, print its result; returns the exit code."""
    argv = list(sys.argv[1:] if argv is None else argv)
    if not argv or argv[0] in ("-h", "--help"):
        print(_usage(), file=sys.stdout if argv else sys.stderr)
        return 0 if argv else 2
    name, options = argv[0], argv[1:]
    if name not in FLOWS:
        print(f"error: unknown flow {name!r}; one of {', '.join(FLOWS)} (python -m flows --help lists them)",
              file=sys.stderr)
        return 2
    quiet_environment()
    asks_help = any(o in ("-h", "--help") for o in options)
    server = None if asks_help else start_api_in_background()
    flow = load_flow(name)
    try:
        args = vars(build_parser(name, flow).parse_args(options))
    except SystemExit:  # a bad option (2) or --help (0): stop the server this call started, if any
        if server is not None:
            wait_all([server])
            stop_api()
        raise
    debug = args.pop("debug")
    refused = _refused(name, args)
    if refused:
        if server is not None:
            wait_all([server])
            stop_api()
        print(f"error: {refused}", file=sys.stderr)
        return 2
    if not debug:
        console_without_tracebacks()
    if server is not None:
        server.result()  # raises what the start raised
    with contextlib.redirect_stdout(sys.stderr):  # stdout carries the JSON alone; prints of libraries go beside logs
        state = flow(**args, return_state=True)
    failed = state.is_failed() or state.is_crashed()
    line = failure_line(state) if failed else None
    printed = {"flow": name, "flow_run_id": str(state.state_details.flow_run_id), "state": state.name,
               "result": carried_result(state) if failed else state.result()}
    print(json.dumps(printed | ({"error": line} if failed else {}), indent=2, default=str))
    if failed:
        print(f"error: {line}", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
