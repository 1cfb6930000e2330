"""The adaptive loop: per-sample step sizes under error control, with dense output.

Each sample has its own time, step size, error control, controller history, counters and
status (`State`), so a sample's result does not depend on what else is in the batch, and a
sample that fails is frozen and marked while the others go on. The step itself, in tensor
code, is `adaptive_step.py`'s; this loop around it does the host-side work.

- One host sync per step: the "anyone still running?" flag and the number of outputs to
  write travel together in one `.tolist()`.
- Dense output uses the method's free interpolant (`dense.py`), so steps are never
  shortened to hit output times.
- Two ways through a step, with the same forward: eagerly (the default), the stages are
  `fused.py`'s autograd nodes, whose backward is written for the tableau, and the step's end
  (`fused.end_step`) selects the next state and writes the outputs it crossed into one
  buffer; compiled, or with `fused=False`, `adaptive_step.attempt_step` records every op on
  autograd's tape, which `torch.compile` takes whole (`Problem.compiler`: dynamo cannot
  trace the fused nodes' shared buffers), and the outputs are gathered once at the end.
- With `solve(..., checkpoints=C)` each step (`loop_step`) runs through
  `checkpoint.Checkpointed`: one autograd node that keeps nothing, rerun in the backward
  pass from a kept state (`replica`: the reruns write their outputs apart).
- For compaction (`solve(..., restrict=...)`) the loop may stop once few samples still run,
  returning each sample's `State` (`Restart`), from which `solve` goes on with those
  samples only: a restart needs no change to either step.
"""

from __future__ import annotations

import copy
from functools import partial
from typing import NamedTuple

import torch

from mpnode_cli.solver.adaptive_step import (
    Attempt,
    Constants,
    State,
    attempt_step,
    control,
    initial_step,
    plan_step,
)
from mpnode_cli.solver.checkpoint import Checkpointed
from mpnode_cli.solver.compile_cache import CompileCache
from mpnode_cli.solver.dense import OutputTimes, dense_weights, gather_outputs, lanes
from mpnode_cli.solver.fused import StepTape, collect_outputs, end_step, fused_stages, start_outputs
from mpnode_cli.solver.problem import Problem
from mpnode_cli.solver.runge_kutta import RHS, Stages, StageTableau
from mpnode_cli.solver.solution import Status


class Restart(NamedTuple):
    """Where a solve that stopped early for compaction left off: what `solve` restarts
    the running samples from (`solve._adaptive`); `[B]` tensors."""

    state: State  # each sample's place, its y and k₁ differentiable
    status: torch.Tensor  # int64 the statuses so far
    n_f: torch.Tensor  # int64 evaluations of f besides the steps' own (k₁, restarts)

    def select(self, index: torch.Tensor) -> Restart:
        """The samples `index` (`[B']` int64) of it."""
        return Restart(State(*(x.index_select(0, index) for x in self.state)),
                       self.status.index_select(0, index), self.n_f.index_select(0, index))


def solve_adaptive(problem: Problem, fun: RHS, shaped: RHS, y: torch.Tensor,
                   start: Restart | None = None):
    """Integrate `problem` with adaptive steps.

    Args:
        problem: the solve's settings (`problem.controller` set).
        fun: the right-hand side on flat states, `fun(t [B], y [B, F]) -> [B, F]`.
        shaped: the same on `[B, *S]` states, for fused steps (`problem.fused`).
        y: `[B, F]` initial states at `ts[0]`.
        start: go on from where an earlier solve of these samples stopped (its `Restart`,
            the samples selected) instead of starting at `ts[0]`; `y` is then its `state.y`.

    Returns:
        `(ys [B, T, F], status [B], stats, restart)`, the first three as `solve` returns
        them, and `restart`, None where the solve ran to the end; else it stopped early for
        compaction (`problem.block`: once the samples still running, counted in whole
        blocks, make at most half of the batch and at least `COMPACT_MIN_DROP` rows could
        be dropped): outputs beyond a running sample's progress are NaN and its stats are
        those so far, and `restart` says where to go on from.
    """
    batch, tab = y.shape[0], problem.tab
    stops_pad = torch.cat([problem.stops, problem.stops[-1:]])  # finished samples: past the end
    state, status, n_f = _first_state(problem, fun, y, stops_pad) if start is None else start
    record = torch.is_grad_enabled() and (state.k1.requires_grad or y.requires_grad)
    stages = tape = None
    if problem.fused and problem.compiler is None:
        tape = StepTape(tab, y, problem.batch_shape(batch), record, problem.ts.numel())
        start_outputs(tape, y)
        steps = FusedSteps(tape, problem.ts, shaped)
    else:
        stages = Stages(tab.stages, batch, y.shape[1], y, not record)
        steps = RecordedSteps(y, problem.ts, tab, problem.compiler)
    consts = Constants(tab, problem.controller, problem.order, stages, tape, problem.ts,
                       stops_pad, problem.stops.numel(), problem.max_steps, problem.block)
    # Stop for compaction when few enough rows still run and enough could be dropped.
    keep_max = (min(int(batch * COMPACT_KEEP_FRACTION), batch - COMPACT_MIN_DROP)
                if problem.block else -1)
    step = partial(loop_step, fun, consts, steps)
    if problem.checkpoints is not None and record:  # steps recomputed in the backward pass
        step = Checkpointed(step, problem.checkpoints, lambda: partial(
            loop_step, fun, consts, steps.replica()))
    state, status, n_f, early = _loop(step, consts, (state, status, n_f), problem.report,
                                      keep_max)
    stats = {"n_steps": state.n_steps, "n_accepted": state.n_accepted,
             "n_rejected": state.n_steps - state.n_accepted,
             "n_f_evals": n_f + (tab.stages - 1) * state.n_steps}
    return steps.result(y, state), status, stats, Restart(state, status, n_f) if early else None


def _first_state(problem: Problem, fun: RHS, y: torch.Tensor, stops_pad: torch.Tensor):
    """`(state, status, n_f)` of the batch at `ts[0]`: f there, the first step size
    (`problem.dt0` or `initial_step`'s), and NON_FINITE where y₀ or f(y₀) is not finite."""
    batch, dev, f64 = y.shape[0], y.device, torch.float64
    t0 = problem.ts[0]
    t = t0.expand(batch).clone()  # (B,) float64
    k1 = fun(t, y)
    n_f = torch.ones(batch, dtype=torch.long, device=dev)
    if problem.dt0 is None:
        span = (problem.ts[-1] - t0).expand(batch)
        dt = initial_step(fun, t, y, k1, problem.controller, span, problem.order)
        n_f += 1
    else:
        dt = torch.as_tensor(problem.dt0, dtype=f64, device=dev).expand(batch).clone()
    stop_idx = torch.zeros(batch, dtype=torch.long, device=dev)
    start_ok = torch.isfinite(k1).all(dim=1) & torch.isfinite(y).all(dim=1)
    status = torch.where(start_ok, Status.SUCCESS, Status.NON_FINITE)
    state = State(
        t=t, dt=dt, y=y, k1=k1, running=start_ok, stop_idx=stop_idx,
        stop_t=stops_pad[stop_idx],
        err_prev=torch.full((batch,), problem.controller.initial_history(), dtype=f64,
                            device=dev),
        n_steps=torch.zeros_like(stop_idx), n_accepted=torch.zeros_like(stop_idx),
        n_nonfinite=torch.zeros_like(stop_idx),
        out_idx=torch.ones(batch, dtype=torch.long, device=dev))
    return state, status, n_f


# Compaction stops a solve only when at least this many rows would be dropped (restarting
# a few rows costs more than it saves), and at most this fraction of its rows still run.
COMPACT_MIN_DROP = 8
COMPACT_KEEP_FRACTION = 0.5


def _loop(step, consts, carry, report, keep_max):
    """Step (`step(carry)`, `loop_step`'s) until no sample runs, or (`keep_max` ≥ 0,
    `consts.block`) until the rows of the blocks that still run are at most `keep_max`;
    returns `(state, status, n_f, stopped early)`."""
    while True:
        carry, flags = step(carry)
        if not flags[0]:
            return (*carry, False)
        if consts.block and flags[4] <= keep_max:
            return (*carry, True)
        if report is not None:
            report(carry[0].t)


def loop_step(fun, consts, steps, carry):
    """One attempted step of the samples that run, and its bookkeeping: `carry` is
    `(state, status, n_f)`; returns the next carry and the step's `control` flags as
    Python ints (its one host sync). What `checkpoint.Checkpointed` reruns."""
    state, status, n_f = carry
    state, flags, step = steps.attempt(fun, consts, state)
    flags = flags.tolist()  # the step's one sync
    _, width, any_jumped, any_failed = flags[:4]
    if any_failed:  # rare: record why those samples stopped
        why = torch.where(step.too_many, Status.NON_FINITE,
                          torch.where(step.underflow, Status.DT_UNDERFLOW, Status.MAX_STEPS))
        status = torch.where(step.failed, why, status)
    state = steps.end(state, step, width)
    if width > 0:
        state = state._replace(out_idx=state.out_idx + step.n_cross)
    if any_jumped:  # right-limit derivative at the stop, for those that landed there
        k1 = torch.where(step.jumped[:, None], fun(state.t, state.y), state.k1)
        n_f = n_f + state.running
        state = state._replace(k1=k1)
    return (state, status, n_f), flags


class RecordedSteps:
    """Steps recorded op by op (`attempt_step`, compiled or not), and their outputs:
    `(column index [B, W], value [B, W, F])` per writing step, scattered into the result
    once at the end (one gather in the backward pass instead of one full-size copy per
    step); a spare column at index T takes the writes of masked-out lanes."""

    def __init__(self, y: torch.Tensor, ts: torch.Tensor, tab: StageTableau,
                 compiler: CompileCache | None):
        """`compiler`: run `attempt_step` through it (None: eagerly)."""
        self.n_out, self.out = ts.numel(), OutputTimes.of(ts, tab)
        self.compiler = compiler
        self.cols = [torch.zeros(y.shape[0], 1, dtype=torch.long, device=y.device)]
        self.vals = [y.unsqueeze(1)]

    def attempt(self, fun: RHS, consts: Constants, state: State):
        """`attempt_step`'s `(state, flags, attempt)`, through the compiler if any."""
        if self.compiler is None:
            return attempt_step(fun, consts, state)
        return self.compiler(attempt_step, fun, consts, state)

    def end(self, state: State, step: Attempt, width: int) -> State:
        """Collect the outputs the step crossed (the step has advanced the state)."""
        if width > 0:
            cols, valid, coef = dense_weights(self.out, step.t, step.h, state.out_idx,
                                              step.n_cross, width)
            coef = coef.to(step.y.dtype)
            self.cols.append(torch.where(valid, cols, self.n_out))
            self.vals.append(lanes(coef, step.hk, step.y))
        return state

    def result(self, y0: torch.Tensor, state: State) -> torch.Tensor:
        """`[B, T, F]` the outputs, NaN where none was written."""
        return gather_outputs(self.cols, self.vals, self.n_out)


class FusedSteps:
    """Steps whose stages are `fused.py`'s autograd nodes; each step's end writes the
    outputs it crossed into the tape's output buffer."""

    def __init__(self, tape: StepTape, ts: torch.Tensor, shaped: RHS):
        batch, dev = tape.shape[0], ts.device
        self.tape, self.shaped = tape, shaped
        self.out = OutputTimes.of(ts, tape.tab)
        self.base = torch.arange(batch, device=dev)[:, None] * ts.numel()  # (B, 1) column 0
        self.spare = batch * ts.numel()  # the output buffer's spare row

    def replica(self) -> FusedSteps:
        """The same steps writing their outputs into a buffer of their own (a checkpointed
        solve's reruns, which must leave the result as it is); their backward reads the
        outputs' gradient as it is now."""
        twin = copy.copy(self)
        twin.tape = copy.copy(self.tape)
        twin.tape.out = torch.empty_like(self.tape.out)
        return twin

    def attempt(self, fun: RHS, consts: Constants, state: State):
        """`control`'s `(state, flags, attempt)`; `end` then advances y and k₁."""
        h, t_new, land = plan_step(state)
        rec, y_new, err, f_new = fused_stages(self.shaped, consts.tab, self.tape, state.t, h,
                                              state.y, state.k1, t_new)
        state, flags, step = control(consts, state, h, t_new, land, y_new, err)
        return state, flags, step._replace(f_new=f_new, rec=rec)

    def end(self, state: State, step: Attempt, width: int) -> State:
        """Advance the accepted samples and write the outputs the step crossed."""
        rows = coef = None
        if width > 0:
            cols, valid, coef = dense_weights(self.out, step.t, step.h, state.out_idx,
                                              step.n_cross, width)
            rows = torch.where(valid, self.base + cols, self.spare).reshape(-1)  # (B·W,)
        y, k1 = end_step(step.rec, step.f_new, step.accept, rows, coef)
        return state._replace(y=y, k1=k1)

    def result(self, y0: torch.Tensor, state: State) -> torch.Tensor:
        """`[B, T, F]` the outputs, NaN where none was written."""
        return collect_outputs(self.tape, y0, state.y, state.k1)
