"""One builder from declarations to command-line options.

A verb that takes a config's fields as options declares them once, on the config (each
pydantic field's description is its help), and lists them by panel, as a user looks for
them: `with_options(command, panels, build)` gives the command (whose `**options` collects
them) its own parameters placed in their panels and, for every other name, the option
`build(name, panel)` makes, usually `field_parameter` of the config's field. An option is
left out as None, so that the config's defaults (and a `--config` file beneath the
options) stay the only defaults. Flags are spelt as `mpnode_cli.flags` declares.
"""

from __future__ import annotations

import copy
import inspect
import types
from collections.abc import Callable
from pathlib import Path
from typing import Annotated, Any, Literal, Union, get_args, get_origin

import typer
from pydantic import BaseModel
from typer.models import ArgumentInfo

from mpnode_cli import flags
from mpnode_cli.cli.common import _number


def with_options(command: Callable, panels: dict[str, tuple[str, ...]],
                 build: Callable[[str, str], inspect.Parameter | None]) -> Callable:
    """`command` with its options in `panels`' order: its own parameters (its arguments
    first) placed in their panels, and `build(name, panel)`'s option for each other name
    (None: the command does not take it).

    Raises:
        TypeError: a parameter of the command that no panel names.
    """
    signature = inspect.signature(command)
    own = {p.name: p for p in signature.parameters.values() if p.kind is not p.VAR_KEYWORD}
    params = [p for p in own.values() if isinstance(p.default, ArgumentInfo)]
    for panel, names in panels.items():
        for name in names:
            if name in own:
                params.append(own[name].replace(kind=inspect.Parameter.KEYWORD_ONLY,
                                                default=in_panel(own[name].default, panel)))
            elif (built := build(name, panel)) is not None:
                params.append(built)
    if missing := set(own) - {p.name for p in params}:
        raise TypeError(f"parameters of {command.__name__} in no panel: {sorted(missing)}")
    command.__signature__ = signature.replace(parameters=params)
    return command


def field_parameter(config: type[BaseModel], name: str, panel: str, *,
                    default: str | None = None, extra: str = "", metavar: str | None = None,
                    value_type: type | None = None, decls: tuple[str, ...] | None = None,
                    parser: Callable[[Any], Any] | None = None,
                    allowed: tuple[str, ...] | None = None) -> inspect.Parameter:
    """The option of `config`'s field `name`: its description, then `extra`, the
    `default` a user gets (None: nothing to say) and its choices (`allowed`, else a
    `Literal`'s) where the description does not name them all. `value_type` (default: the
    field's type) is what the command line hands over, `str` for a choice."""
    field = config.model_fields[name]
    named = choices(field.annotation) if allowed is None else allowed
    value_type = value_type or (str if named else plain(field.annotation))
    text = " ".join(part for part in (field.description or "", extra) if part)
    help_text = " ".join(part for part in (
        text if default is None else f"{text.removesuffix('.')} (default {default}).",
        None if all(c in text for c in named) else f"Choices: {', '.join(named)}.",
    ) if part)
    return parameter(name, value_type, decls or flags.decls(name, value_type is bool),
                     help_text, panel, metavar=metavar, parser=parser,
                     required=field.is_required())


def field_default(config: type[BaseModel], name: str) -> str | None:
    """A field's own default as `--help` shows it (a tuple as the command line writes it,
    `0.7,0.15,0.15`); None for a required field, a default of None, or a switch's off."""
    field = config.model_fields[name]
    if field.is_required() or field.default is None or field.default is False:
        return None
    if isinstance(field.default, tuple):
        return ",".join(str(v) for v in field.default)
    return shown(field.default)


def parameter(name: str, value_type: type, decls: tuple[str, ...], help_text: str,
              panel: str, *, metavar: str | None = None,
              parser: Callable[[Any], Any] | None = None,
              required: bool = False) -> inspect.Parameter:
    """A keyword parameter whose typer option is left out as None, or must be given
    (`required`)."""
    if value_type not in (bool, int, float, str, Path):
        raise TypeError(f"option '{name}' has a type the CLI cannot take: {value_type}")
    option = typer.Option(... if required else None, *decls, help=help_text,
                          rich_help_panel=panel, parser=parser, metavar=metavar,
                          show_default=not required)
    return inspect.Parameter(name, inspect.Parameter.KEYWORD_ONLY, default=option,
                             annotation=value_type if required else value_type | None)


def in_panel(option: Any, panel: str) -> Any:
    """A copy of a declared typer option, shown in `panel` (`THREADS` and the solver's
    options serve several verbs as they are)."""
    option = copy.copy(option)
    option.rich_help_panel = panel
    return option


def choices(annotation: Any) -> tuple[str, ...]:
    """A `Literal`'s values (nothing for another type)."""
    return get_args(annotation) if get_origin(annotation) is Literal else ()


def plain(annotation: Any) -> Any:
    """`int` of `int | None`, `str` of `Annotated[str, ...]`; other types as they are."""
    if get_origin(annotation) in (Union, types.UnionType):
        (annotation,) = [a for a in get_args(annotation) if a is not type(None)]
    return get_args(annotation)[0] if get_origin(annotation) is Annotated else annotation


def shown(value: Any) -> str:
    """A default as `--help` shows it: on/off for a flag, numbers short."""
    if isinstance(value, bool):
        return "on" if value else "off"
    return _number(value)
