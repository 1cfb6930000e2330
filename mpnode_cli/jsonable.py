"""Values as JSON can hold them: `jsonable(value)`.

JSON has no NaN or infinity (RFC 8259, section 6); Python's `json` writes them anyway, as
tokens other readers reject. A metric that is undefined (every rollout failed, an empty
split) is therefore written as null, and read back as None.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any


def jsonable(value: Any) -> Any:
    """`value` with every non-finite float as None and every `Path` as its string, through
    dicts, lists and tuples (a tuple becomes a list, as `json` writes it)."""
    if isinstance(value, float):
        return value if math.isfinite(value) else None
    if isinstance(value, dict):
        return {k: jsonable(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [jsonable(v) for v in value]
    if isinstance(value, Path):
        return str(value)
    return value
