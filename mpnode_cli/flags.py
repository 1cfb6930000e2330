"""How a config field is spelt on the command line, declared once for the verbs' options
(`mpnode_cli.cli.train`) and for the command lines the experiment reports give
(`mpnode_cli.experiments.commands`).

A field is `--name VALUE` (underscores as hyphens). A boolean is the switch pair
`--name/--no-name`, unless `SWITCHES` names its two spellings; None for off is a switch
that only turns something on (leaving it out is off).
"""

from __future__ import annotations

from typing import Any

SWITCHES: dict[str, tuple[str, str | None]] = {
    "even_batches": ("--even-batches", "--tail-batch"),
    "stream": ("--stream", "--in-memory"),
    "renormalize": ("--renormalize", None),
    "allow_other_system": ("--allow-other-system", None),
    "allow_predictions": ("--allow-predictions", None),
    "directed": ("--directed", None),
}


def flag(name: str) -> str:
    """`--name` of field `name`."""
    return "--" + name.replace("_", "-")


def switch(name: str) -> tuple[str, str | None]:
    """The spellings of boolean field `name` on and off (None: no spelling for off)."""
    return SWITCHES.get(name, (flag(name), "--no-" + flag(name)[2:]))


def decls(name: str, boolean: bool) -> tuple[str, ...]:
    """The option's declaration for typer: `("--on/--off",)`, `("--on",)` or `("--name",)`."""
    if not boolean:
        return (flag(name),)
    on, off = switch(name)
    return (f"{on}/{off}",) if off else (on,)


def words(name: str, value: Any) -> list[str]:
    """The words that give field `name` the value `value` (nothing for a switch's off that
    has no spelling: leaving it out is off)."""
    if isinstance(value, bool):
        on, off = switch(name)
        return [on] if value else ([off] if off else [])
    if isinstance(value, list | tuple):
        return [flag(name), ",".join(str(v) for v in value)]
    return [flag(name), str(value)]
