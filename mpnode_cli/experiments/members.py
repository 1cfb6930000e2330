"""An ensemble's results member by member, and what a claim says over the members.

`mpnode experiment run NAME --seeds S` trains every training step as an ensemble of S
members (`mpnode train --seeds S`: member k has the seed seed + k; a finetune's member k
starts from its parent's member k). A step whose numbers come from a trained model then
carries, beside its own result, `members`: S dicts with the same keys as a single model's
result, each member's alone (a training's best epoch, minimum validation loss, Table-2
figure and test MSE; an evaluation's errors; a comparison's runs, member k of each). Member
k of one step goes with member k of every other.

A claim `LEFT OP RIGHT` is judged on each member alone and on the members' means
(`decide_pairs`):

- it **holds** when it holds for every member, or when the means differ by more than the
  combined std, sqrt(std_left² + std_right²), the claimed way;
- it **fails** when it fails for every member, or when the means differ by more than the
  combined std the other way;
- otherwise it is **undecided**: the members disagree and their spread covers the gap.

Stds are population stds over the members. A result without `members` (one seed, and every
report written before seeds) is one member, so a claim on it holds or fails.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

MEMBERS = "members"
OPS = {"<": float.__lt__, ">": float.__gt__, "<=": float.__le__, ">=": float.__ge__}


def count(results: Mapping[str, Any]) -> int:
    """S, the members of the results' ensembles (step id → result): 1 when none has any.

    Raises:
        ValueError: results whose ensembles differ in size (their members cannot be paired).
    """
    sizes = {len(r[MEMBERS]) for r in results.values() if isinstance(r, dict) and r.get(MEMBERS)}
    if len(sizes) > 1:
        raise ValueError(f"results of ensembles of {sorted(sizes)} members: member k of one "
                         "has no member k in another")
    return sizes.pop() if sizes else 1


def of(result: Any, k: int) -> Any:
    """Member k's result: `result["members"][k]`, or the result itself when it has no
    members (a generate step's, or a single model's)."""
    rows = result.get(MEMBERS) if isinstance(result, dict) else None
    return rows[k] if rows else result


def view(results: Mapping[str, Any], k: int) -> dict[str, Any]:
    """Step id → member k's result: the results as if member k had been trained alone."""
    return {step: of(result, k) for step, result in results.items()}


def lookup(result: Any, path: str) -> Any:
    """The value at the dotted `path` (`test.mse`) of a result, or None."""
    for key in path.split("."):
        result = result.get(key) if isinstance(result, dict) else None
    return result


def values(result: Any, path: str) -> list[Any]:
    """The value at `path` in each member's result; one value for a result without members."""
    rows = result.get(MEMBERS) if isinstance(result, dict) else None
    return [lookup(row, path) for row in (rows or [result])]


def _number(value: Any) -> bool:
    return isinstance(value, int | float) and not isinstance(value, bool)


def mean_and_std(numbers: Sequence[Any]) -> tuple[float, float] | None:
    """Mean and population std of `numbers`; None if one is missing (not a number)."""
    if not numbers or not all(_number(x) for x in numbers):
        return None
    mean = math.fsum(numbers) / len(numbers)
    return mean, math.sqrt(math.fsum((x - mean) ** 2 for x in numbers) / len(numbers))


def shown(numbers: Sequence[Any], digits: int = 4) -> str:
    """`0.1234 ± 0.012` over several members, `0.1234` for one, `—` with one missing."""
    stats = mean_and_std(numbers)
    if stats is None:
        return "—"
    mean, std = stats
    if len(numbers) == 1:
        return f"{mean:.{digits}g}"
    return f"{mean:.{digits}g} ± " + (f"{std:.0f}" if std >= 100 else f"{std:.2g}")


@dataclass(frozen=True)
class Decision:
    """A claim over the members.

    Attributes:
        outcome: "holds", "fails", "undecided", or None when a number is missing.
        pairs: each member's two sides (None where missing).
        op: the comparison, `<`, `>`, `<=` or `>=`.
        held: the members for which it holds.
        apart: +1 when the means differ by more than the combined std the claimed way, -1
            the other way, 0 when they do not (or a number is missing).
    """

    outcome: str | None
    pairs: list[tuple[float | None, float | None]]
    op: str
    held: int
    apart: int

    @property
    def members(self) -> int:
        return len(self.pairs)

    def shown(self) -> str:
        """The two sides as mean ± std: `0.1 ± 0.01 < 0.3 ± 0.02`."""
        return f" {self.op} ".join(shown([pair[side] for pair in self.pairs]) for side in (0, 1))

    def by_member(self) -> str:
        """Each member's comparison, `0.09 < 0.31; 0.11 > 0.1`, each side as `judge` shows it."""
        return "; ".join(f" {self.op} ".join("—" if v is None else f"{v:.4g}" for v in pair)
                         for pair in self.pairs)

    def reason(self) -> str:
        """What the outcome rests on: `holds for 3 of 3 members`, or when the members split
        `holds for 2 of 3 members; the means differ by less than their combined std`."""
        if self.outcome is None:
            return "a number missing"
        held = f"holds for {self.held} of {self.members} members"
        if self.held in (0, self.members):
            return held
        return held + {1: "; the means differ by more than their combined std, the claimed way",
                       -1: "; the means differ by more than their combined std, the other way",
                       0: "; the means differ by less than their combined std"}[self.apart]


def decide_pairs(pairs: Sequence[tuple[float | None, float | None]], op: str) -> Decision:
    """The verdict of `LEFT op RIGHT` from each member's two sides (the module's rule)."""
    pairs = list(pairs)
    if not pairs or any(v is None for pair in pairs for v in pair):
        return Decision(None, pairs, op, 0, 0)
    held = sum(OPS[op](float(a), float(b)) for a, b in pairs)
    left, right = mean_and_std([a for a, _ in pairs]), mean_and_std([b for _, b in pairs])
    assert left is not None and right is not None  # every value is a number
    gap = right[0] - left[0] if op in ("<", "<=") else left[0] - right[0]
    combined = math.hypot(left[1], right[1])
    apart = 1 if gap > combined else -1 if -gap > combined else 0
    # Every member holding puts the means the claimed way, so the two rules never clash.
    if held == len(pairs) or apart > 0:
        outcome = "holds"
    elif held == 0 or apart < 0:
        outcome = "fails"
    else:
        outcome = "undecided"
    return Decision(outcome, pairs, op, held, apart)
