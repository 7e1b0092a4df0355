"""Flow parameters declared by the library's options models, as the command line's options are.

Prefect reads each parameter's description from the ``Args:`` section of the flow function's docstring (into its
parameter schema, which the UI and ``python -m flows FLOW --help`` show); :func:`declared_parameters` writes
that section from the models' field descriptions, so a flow's help and ``mpi-lidar``'s say the same.
"""

from __future__ import annotations

import inspect
from collections.abc import Callable, Sequence
from typing import TypeVar

from pydantic import BaseModel

from mpi_lidar.correction.options import UserOption

F = TypeVar("F", bound=Callable[..., object])


def declared_parameters(*declarations: tuple[type[BaseModel], Sequence[UserOption]]) -> Callable[[F], F]:
    """Add each declared option's help to the flow function's ``Args:`` section (apply it below ``@flow``).

    A function without a parameter of a declared option's name is refused when its module imports.
    """
    def document(fn: F) -> F:
        parameters = inspect.signature(fn).parameters
        declared = [(model, option) for model, options in declarations for option in options]
        missing = [option.name for _, option in declared if option.name not in parameters]
        if missing:
            raise TypeError(f"{fn.__qualname__} lacks the declared parameters {', '.join(missing)}")
        doc = inspect.getdoc(fn) or ""
        head = doc if "\nArgs:\n" in doc else f"{doc}\n\nArgs:"
        fn.__doc__ = "\n".join([head, *(f"    {option.name}: {_help(model, option, parameters[option.name])}"
                                        for model, option in declared)])
        return fn
    return document


def _help(model: type[BaseModel], option: UserOption, parameter: inspect.Parameter) -> str:
    """The option's help, and what None stands for where the flow's default is None and the field's is not."""
    stands_for = parameter.default is None and model.model_fields[option.field].default is not None
    return option.help_text(model) + (f" (None: {option.default_said(model)})" if stands_for else "")


def description(doc: str | None) -> str:
    """A flow's docstring without its ``Args:`` section (each parameter's help is shown beside its option)."""
    return (doc or "").split("\nArgs:\n", 1)[0].rstrip()
