"""Fixed steps: no error control, steps of at most `fixed_dt` that hit every output time
and every stop exactly (the only way to run a method without an error estimate, e.g. RK4).

The step grid is the same for every sample, so it is a Python list and the loop needs no
host sync; a sample whose state turns non-finite is frozen and marked `NON_FINITE`. With
`solve(..., checkpoints=C)` each step (`fixed_step`) runs through `checkpoint.Checkpointed`.
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Iterator
from functools import partial

import torch

from mpnode_cli.solver.checkpoint import Checkpointed
from mpnode_cli.solver.fused import StepTape, end_step, fused_stages
from mpnode_cli.solver.problem import Problem
from mpnode_cli.solver.runge_kutta import RHS, Stages, rk_step
from mpnode_cli.solver.solution import Status


def fixed_grid(ts: torch.Tensor, stops: torch.Tensor, fixed_dt: float) -> Iterator[float]:
    """Step end times: every output time and stop, with equal substeps of ≤ fixed_dt between.

    Yielded one at a time: a tiny `fixed_dt` makes billions of them, and the solve stops at
    `max_steps` long before (as a list they once filled the memory first).
    """
    marks = torch.unique(torch.cat([ts, stops])).tolist()
    for a, b in itertools.pairwise(marks):
        n = max(1, math.ceil((b - a) / fixed_dt - 1e-9))
        yield from (a + (b - a) * (i / n) for i in range(1, n))
        yield b


def solve_fixed(problem: Problem, fun: RHS, shaped: RHS, y: torch.Tensor):
    """Integrate `problem` with fixed steps of at most `problem.fixed_dt`.

    Args:
        problem: the solve's settings (`problem.fixed_dt` set).
        fun: the right-hand side on flat states, `fun(t [B], y [B, F]) -> [B, F]`.
        shaped: the same on `[B, *S]` states, for fused steps (`problem.fused`, `fused.py`);
            else every op of the step is recorded.
        y: `[B, F]` initial states at `ts[0]`.

    Returns:
        `(ys [B, T, F], status [B], stats)`, as `solve` returns them.
    """
    tab, ts, stops, report = problem.tab, problem.ts, problem.stops, problem.report
    batch = y.shape[0]
    dev = y.device
    n_out = ts.numel()
    out_times = ts.tolist()
    grid = fixed_grid(ts, stops, problem.fixed_dt)
    interior_stops = set(stops[:-1].tolist())
    zero = torch.zeros((), dtype=torch.float64, device=dev)
    n_extra = 0

    t_prev = out_times[0]
    t = torch.full((batch,), t_prev, dtype=torch.float64, device=dev)
    k1 = fun(t, y)
    advance = _stepper(problem, fun, shaped if problem.fused else None, y, k1)
    running = torch.isfinite(k1).all(dim=1) & torch.isfinite(y).all(dim=1)
    status = torch.where(running, Status.SUCCESS, Status.NON_FINITE)
    n_steps = torch.zeros(batch, dtype=torch.long, device=dev)
    outs = [y] + [None] * (n_out - 1)
    nan_row = torch.full_like(y, math.nan)
    step = partial(fixed_step, advance, fun, zero)
    if problem.checkpoints is not None and torch.is_grad_enabled() and (
            k1.requires_grad or y.requires_grad):  # steps recomputed in the backward pass
        step = Checkpointed(step, problem.checkpoints)
    j = 1
    for i, t_next in enumerate(grid):
        if i >= problem.max_steps:
            status = torch.where(running, Status.MAX_STEPS, status)
            running = torch.zeros_like(running)
            break
        stop = t_next in interior_stops
        (t, y, k1, ok), _ = step((t, y, k1, running), t_prev, t_next, stop)
        status = torch.where(running & ~ok, Status.NON_FINITE, status)
        n_steps += running
        running = ok
        t_prev = t_next
        n_extra += stop
        if j < n_out and t_next == out_times[j]:
            # Samples that already failed report NaN from here on, like the adaptive solver.
            outs[j] = torch.where(running[:, None], y, nan_row)
            j += 1
        if report is not None:
            report(t)
    outs[j:] = [nan_row] * (n_out - j)
    ys = torch.stack(outs, dim=1)  # (B, T, F)
    stats = {"n_steps": n_steps, "n_accepted": n_steps.clone(),
             "n_rejected": torch.zeros_like(n_steps),
             "n_f_evals": 1 + (tab.stages - 1) * n_steps + n_extra}
    return ys, status, stats


def fixed_step(advance, fun: RHS, zero: torch.Tensor, carry, t_prev: float, t_next: float,
               stop: bool):
    """One step of every running sample from `carry = (t, y, k1, running)` (`[B]`,
    `[B, F]`, `[B, F]`, `[B]`), all at `t_prev`, to `t_next`, f re-evaluated there if it is
    an interior `stop`: the next carry (running: still finite) and None. What
    `checkpoint.Checkpointed` reruns."""
    t, y, k1, running = carry
    h = torch.where(running, t_next - t_prev, zero)
    t_end = torch.full_like(t, t_next)
    y, k1, ok = advance(t, h, y, k1, t_end, running)
    if stop:  # f may jump here: FSAL's left limit is not valid
        k1 = fun(t_end, y)
    return (t_end, y, k1, ok), None


def _stepper(problem: Problem, fun: RHS, shaped: RHS | None, y: torch.Tensor,
             k1: torch.Tensor):
    """`advance(t, h, y, k1, t_end, running) -> (y, k1, ok)`: one step of every sample,
    recorded op by op (`shaped` None) or fused; `ok` `[B]`: running and finite after it,
    the others kept where they were."""
    tab, batch = problem.tab, y.shape[0]
    record = torch.is_grad_enabled() and (k1.requires_grad or y.requires_grad)
    if shaped is None:
        stages = Stages(tab.stages, batch, y.shape[1], y, reuse=not record)
    else:
        tape = StepTape(tab, y, problem.batch_shape(batch), record)

    def finite(running, y_new, f_new):
        return (running & torch.isfinite(y_new).all(dim=1)
                & torch.isfinite(f_new).flatten(1).all(dim=1))

    def recorded(t, h, y, k1, t_end, running):
        y_new, _, f_new, _ = rk_step(fun, tab, stages, t, h, y, k1, t_end)
        ok = finite(running, y_new, f_new)
        return torch.where(ok[:, None], y_new, y), torch.where(ok[:, None], f_new, k1), ok

    def fused(t, h, y, k1, t_end, running):
        rec, y_new, _, f_new = fused_stages(shaped, tab, tape, t, h, y, k1, t_end)
        ok = finite(running, y_new, f_new)
        return (*end_step(rec, f_new, ok), ok)

    return recorded if shaped is None else fused
