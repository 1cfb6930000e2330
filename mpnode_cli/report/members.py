"""How outputs show an ensemble's members (`train --seeds S`).

Training and evaluation treat a single model as an ensemble of one and compute every
member's numbers alike. What differs is only what is shown: a single model's outputs name
no member and carry no members' statistics (a spread of one is 0, a mean ± std of one is
the number itself), so they read as they did before ensembles. These two functions are
where that is decided.
"""

from __future__ import annotations

from typing import TypeVar

T = TypeVar("T")


def shown(members: int, value: T) -> T | None:
    """`value` (the members' numbers, or a member's) where there are several members to
    tell apart; None for a single model."""
    return value if members > 1 else None


def about_member(k: int, members: int, text: str, sep: str = ": ") -> str:
    """`text` about member k: after the member's number in an ensemble's messages, as it is
    for a single model."""
    return f"member {k}{sep}{text}" if members > 1 else text
