"""A run's stiffness account: one warning when its training rollouts' right-hand-side
evaluations per trajectory sample (`rhs_evals_per_sample` of the epochs' rows, which the
horizon curriculum does not change) have grown tenfold: the learned field is stiffening,
and its steps cost ever more time and, without checkpointed backprop, memory.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

GROWTH = 10  # the growth over the first epoch that warns

ADVICE = ("--max-steps bounds a rollout's steps (a batch that reaches it is skipped), and a "
          "tighter --clip slows the weights' growth")


class Stiffness:
    """Passes a run's events on to `emit`, and after an epoch's row warns once, where its
    evaluations per sample reach `GROWTH` times the first epoch's (this process's first:
    a resumed run's first resumed one)."""

    def __init__(self, emit: Callable[[dict[str, Any]], None]):
        self._emit, self.first, self.warned = emit, None, False

    def emit(self, event: dict[str, Any]) -> None:
        self._emit(event)
        per = event.get("rhs_evals_per_sample") if event.get("event") == "epoch" else None
        if not per or self.warned:
            return
        if self.first is None:
            self.first = (event["epoch"], per)
        elif per >= GROWTH * self.first[1]:
            (epoch, first), self.warned = self.first, True
            self._emit({"event": "warning", "text": (
                f"the training rollouts' right-hand-side evaluations per sample grew "
                f"{per / first:.0f}× since epoch {epoch} ({first:.3g} → {per:.3g}): the "
                f"learned field is stiffening and epochs take longer; {ADVICE}")})
