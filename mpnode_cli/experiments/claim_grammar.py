"""The grammar of a claim's `holds`: `LEFT OP RIGHT`, each side a number or `[FACTOR *]
STEP.PATH` (a value in a step's results)."""

from __future__ import annotations

import re

_NUMBER = r"[-+0-9.eE]+"
_REF = r"[a-z0-9][a-z0-9-]*(?:\.[A-Za-z0-9_-]+)+"  # STEP.PATH
_SIDE = rf"\s*(?:(?P<{{0}}f>{_NUMBER})\s*\*\s*)?(?P<{{0}}>{_NUMBER}|{_REF})\s*"
_CLAIM = re.compile(_SIDE.format("a") + r"(?P<op><=|>=|<|>)" + _SIDE.format("b") + "$")


def parse_claim(text: str) -> tuple[tuple[float, str | None], str, tuple[float, str | None]]:
    """`"2 * a.x < b.y"` → `((2.0, "a.x"), "<", (1.0, "b.y"))`; a number side has ref None
    and the number as its factor.

    Raises:
        ValueError: text that is not `LEFT OP RIGHT`.
    """
    match = _CLAIM.match(text)
    if not match:
        raise ValueError(f"claim '{text}' is not LEFT OP RIGHT (e.g. 'a.test.mse < b.test.mse')")

    def side(name: str) -> tuple[float, str | None]:
        factor, value = match[name + "f"], match[name]
        try:
            return float(value) * float(factor or 1), None
        except ValueError:
            return float(factor or 1), value

    return side("a"), match["op"], side("b")
