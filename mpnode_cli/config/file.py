"""Config files in and config errors out: a verb's `--config` file read as raw fields
(TOML, or JSON such as a dataset's stored `config`), and a pydantic error said in one line.
"""

from __future__ import annotations

import json
import tomllib
from pathlib import Path
from typing import Any

from pydantic import ValidationError

from mpnode_cli.textfiles import read_text


def read_config_file(path: str | Path) -> dict[str, Any]:
    """Read a config file's fields: TOML, or JSON (e.g. a dataset's stored `config`).

    Args:
        path: `.toml` or `.json` file whose top-level keys are config fields.

    Returns:
        The raw fields, to be merged with presets and options and then validated.

    Raises:
        ValueError: a missing file, or one that does not parse.
    """
    path = Path(path)
    text = read_text(path, "config file")
    try:
        if path.suffix == ".json":
            data = json.loads(text)
        else:
            data = tomllib.loads(text)
    except (tomllib.TOMLDecodeError, json.JSONDecodeError) as exc:
        raise ValueError(f"config file {path} does not parse: {exc}") from None
    if not isinstance(data, dict):
        raise ValueError(f"config file {path} must hold a table of fields")
    return data


def error_line(exc: ValidationError) -> str:
    """One line for a user out of a pydantic error: the first problem, where and what.

    Example: `trajectories: Input should be greater than or equal to 1 (got -5)`.
    """
    err = exc.errors()[0]
    msg = str(err["msg"]).removeprefix("Value error, ")
    loc = ".".join(str(p) for p in err["loc"])
    if err["type"] == "extra_forbidden":
        return f"unknown config field '{loc}'"
    if err["type"] == "missing":
        return f"missing config field '{loc}'"
    # Our own ValueErrors already quote the value; pydantic's built-in ones do not.
    quoted = err["type"] == "value_error" or isinstance(err.get("input"), dict)
    got = "" if quoted else f" (got {err['input']!r})"
    return f"{loc}: {msg}{got}" if loc else msg
