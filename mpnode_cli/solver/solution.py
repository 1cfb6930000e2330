"""What a solve returns: the `Solution` and the per-sample `Status` codes.

Apart from `solve.py`, so that the loops that write the codes (`adaptive.py`, `fixed.py`)
import them without importing the entry point that calls them.
"""

from __future__ import annotations

from dataclasses import dataclass
from enum import IntEnum

import torch


class Status(IntEnum):
    """Per-sample outcome of a solve. The solver never raises for numerical failure."""

    SUCCESS = 0
    MAX_STEPS = 1
    DT_UNDERFLOW = 2
    NON_FINITE = 3

    @property
    def message(self) -> str:
        return _STATUS_MESSAGES[self]


_STATUS_MESSAGES = {
    Status.SUCCESS: "solved to the last output time",
    Status.MAX_STEPS: (
        "hit max_steps before the last output time: raise max_steps, loosen rtol/atol, or "
        "check whether the problem is stiff (an explicit solver then needs tiny steps)"
    ),
    Status.DT_UNDERFLOW: (
        "the step size fell below the resolution of the time variable: the solution is "
        "probably blowing up or the problem is stiff; check the model or shorten t_eval"
    ),
    Status.NON_FINITE: (
        "the right-hand side returned NaN/inf even for tiny steps (or at the initial "
        "state): check the initial state and the model for overflow or singularities"
    ),
}

STAT_NAMES = ("n_steps", "n_accepted", "n_rejected", "n_f_evals")


@dataclass(frozen=True)
class Solution:
    """Result of `solve`.

    Attributes:
        ts: `[T]` float64, the output times (`t_eval`).
        ys: `[B, T, *S]` states at `ts`; outputs a failed sample never reached are NaN.
        status: `[B]` int64, a `Status` per sample.
        stats: per-sample int64 `[B]` counters `n_steps` (attempted), `n_accepted`,
            `n_rejected` and `n_f_evals` (right-hand-side calls that included the sample).
    """

    ts: torch.Tensor
    ys: torch.Tensor
    status: torch.Tensor
    stats: dict[str, torch.Tensor]

    @property
    def success(self) -> torch.Tensor:
        """`[B]` bool, True where the sample reached the last output time."""
        return self.status == Status.SUCCESS
