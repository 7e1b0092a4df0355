"""Click options made from the fields of an options model: their help is the field's description, their choices
its enum's, their bounds its own (:class:`~mpi_lidar.correction.options.UserOption` names each option).

The models' modules import numpy and the correction's modules, which ``mpi-lidar --help`` has no need of: a
:class:`DeclaredCommand` builds its options the first time they are asked for.
"""

from __future__ import annotations

import types
import typing
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import click
from pydantic import BaseModel, TypeAdapter
from pydantic.fields import FieldInfo

if typing.TYPE_CHECKING:
    from click.types import OptionHelpExtra

    from mpi_lidar.correction.options import UserOption


class DeclaredCommand(click.Command):
    """A command whose own parameters come first, then those that ``declared()`` builds, when first asked for."""

    def __init__(self, *args: Any, declared: Callable[[], list[click.Parameter]], **kwargs: Any) -> None:
        self._declare = declared
        self._own: list[click.Parameter] = []
        self._all: list[click.Parameter] | None = None
        super().__init__(*args, **kwargs)

    @property  # click sets and reads an attribute: this one is built when first read
    def params(self) -> list[click.Parameter]:
        if self._all is None:
            self._all = [*self._own, *self._declare()]
        return self._all

    @params.setter
    def params(self, value: list[click.Parameter]) -> None:
        self._own, self._all = value, None


class DeclaredOption(click.Option):
    """An option whose ``--help`` says its default in the declaration's words where its value is None (the
    field's default, or a sensor profile's, applies); click would put such a text in parentheses."""

    def __init__(self, *args: Any, default_said: str | None = None, **kwargs: Any) -> None:
        self.default_said = default_said
        super().__init__(*args, **kwargs)

    def get_help_extra(self, ctx: click.Context) -> OptionHelpExtra:
        extra = super().get_help_extra(ctx)
        if self.default_said is not None:
            extra["default"] = self.default_said
        return extra


def declared_options(model: type[BaseModel], declared: Sequence[UserOption]) -> list[click.Parameter]:
    """An option per declared field of ``model``, in the declaration's order."""
    return [_option(model, option) for option in declared]


def _option(model: type[BaseModel], option: UserOption) -> DeclaredOption:
    info = model.model_fields[option.field]
    item, multiple = _item(info.annotation)
    settings: dict[str, Any] = {"help": option.help_text(model), "metavar": option.metavar}
    choices = _choices(item)
    if choices:
        settings |= {"type": click.Choice(choices)}
        if multiple:
            settings |= {"multiple": True, "callback": _none_if_empty if info.default is None else None}
        else:
            settings |= {"default": _value(info.default), "show_default": True}
    elif item is bool:
        settings |= {"is_flag": True}
    elif item is int:
        low, high, low_open, high_open = _bounds(info, 1)
        settings |= {"type": click.IntRange(None if low is None else int(low), None if high is None else int(high),
                                            low_open, high_open),
                     "default": info.default, "show_default": True}
    elif item is float:
        settings |= {"type": click.FloatRange(*_bounds(info, option.per_field_unit)),
                     "default_said": option.default_said(model)}
    elif item is Path:
        settings |= {"type": click.Path(path_type=Path)}
    elif info.default is not None:  # a number or "auto": read as text, checked by the model
        settings |= {"default_said": option.default_said(model)}
    return DeclaredOption([option.flag, option.name], **settings)


def bounded(declared: object) -> click.IntRange | click.FloatRange:
    """The click type of a number declared with its bounds: an ``Annotated[int, Field(ge=...)]`` (as
    :mod:`mpi_lidar.workflows.job_options` declares them) or a model's field (``DatasetConfig.model_fields[...]``)."""
    info = declared if isinstance(declared, FieldInfo) else FieldInfo.from_annotation(declared)  # type: ignore[arg-type]
    low, high, low_open, high_open = _bounds(info, 1)
    if info.annotation is int:
        return click.IntRange(None if low is None else int(low), None if high is None else int(high), low_open,
                              high_open)
    return click.FloatRange(low, high, low_open, high_open)


def _item(annotation: Any) -> tuple[Any, bool]:
    """The type of one value of ``annotation`` without None, and whether it holds several (a tuple)."""
    if typing.get_origin(annotation) in (typing.Union, types.UnionType):
        kept = [a for a in typing.get_args(annotation) if a is not type(None)]
        annotation = kept[0] if len(kept) == 1 else annotation
    if typing.get_origin(annotation) is tuple:
        return typing.get_args(annotation)[0], True
    return annotation, False


def _choices(item: Any) -> list[str] | None:
    """The values an enum (or a type whose schema lists its values) allows; None for any other type."""
    if item in (bool, int, float, str, Path):
        return None
    enum = TypeAdapter(item).json_schema().get("enum")
    return None if enum is None else [str(value) for value in enum]


def _bounds(info: FieldInfo, per_field_unit: float) -> tuple[float | None, float | None, bool, bool]:
    """The field's bounds in the option's unit: lowest, highest, and whether either is excluded."""
    found = {name: getattr(meta, name) for meta in info.metadata for name in ("ge", "gt", "le", "lt")
             if getattr(meta, name, None) is not None}
    low, high = found.get("ge", found.get("gt")), found.get("le", found.get("lt"))
    return _in_unit(low, per_field_unit), _in_unit(high, per_field_unit), "gt" in found, "lt" in found


def _in_unit(bound: float | None, per_field_unit: float) -> float | None:
    """A bound in the option's unit, a whole number as an int (``--help`` says 0<=x<=1000, not 0.0<=x<=1000.0)."""
    if bound is None:
        return None
    value = bound * per_field_unit
    return int(value) if float(value).is_integer() else value


def _value(default: Any) -> Any:
    return getattr(default, "value", default)


def _none_if_empty(_ctx: click.Context, _param: click.Parameter, value: tuple[str, ...]) -> tuple[str, ...] | None:
    """A repeatable option given no time: None, which leaves the choice to the default."""
    return value or None
