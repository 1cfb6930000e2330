"""`Problem`: what one solve integrates and how, as one frozen value.

`solve` checks its arguments and builds one `Problem`; the loops (`adaptive.solve_adaptive`,
`fixed.solve_fixed`) and compaction's restarts (`solve._adaptive`) read it instead of a
list of positional arguments. What changes from one restart to the next (the right-hand
side, the samples' states) is passed beside it.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import torch

from mpnode_cli.solver.compile_cache import CompileCache
from mpnode_cli.solver.controller import StepController
from mpnode_cli.solver.runge_kutta import RHS, StageTableau


@dataclass(frozen=True, kw_only=True)
class Problem:
    """One solve's settings, shared by the batch (and by compaction's restarts).

    Attributes:
        tab: the method's constants in the solve's dtype and device.
        ts: `[T]` float64 output times, `ts[0]` the start.
        stops: sorted float64 times in (t0, t_end] that steps land on, t_end last.
        shape: `S`, one sample's state shape (`y0: [B, *S]`).
        dtype: the states' dtype.
        max_steps: attempted steps per sample before it is marked `MAX_STEPS`.
        fused: take steps as `fused.py`'s autograd nodes (else recorded op by op).
        report: called with each sample's time `[B]` after every step (`solve._Reporter`).
        controller: the adaptive steps' step-size controller, with its tolerances (None:
            fixed steps).
        order: p, the error estimate's order + 1, which the controller and the first
            step's heuristic take.
        dt0: the first step size, scalar or `[B]`, or None for Hairer's heuristic.
        compiler: run the adaptive step through `torch.compile`, with this cache of its
            compiled graphs and its eager fallback (None: eagerly).
        restrict: `restrict(index) -> f'`, the right-hand side of the samples `index` alone
            (compaction; None: none).
        block: compaction keeps or drops whole blocks of this many samples (0: no
            compaction).
        fixed_dt: the largest fixed step (None: adaptive steps).
        checkpoints: keep at most this many solver states and no step's saved tensors,
            recomputing the steps in the backward pass (`checkpoint.py`); None: plain
            backpropagation.
    """

    tab: StageTableau
    ts: torch.Tensor
    stops: torch.Tensor
    shape: tuple[int, ...]
    dtype: torch.dtype
    max_steps: int
    fused: bool
    report: Callable[[torch.Tensor], None] | None = None
    controller: StepController | None = None
    order: int = 0
    dt0: float | torch.Tensor | None = None
    compiler: CompileCache | None = None
    restrict: Callable[[torch.Tensor], RHS] | None = None
    block: int = 0
    fixed_dt: float | None = None
    checkpoints: int | None = None

    def batch_shape(self, batch: int) -> tuple[int, ...]:
        """`(B, *S)`, the states' shape as f sees them, for a batch of `batch` samples."""
        return (batch, *self.shape)
