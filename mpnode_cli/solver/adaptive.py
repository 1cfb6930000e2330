"""The adaptive loop: per-sample step sizes under error control, with dense output.

Each sample has its own time, step size, error control, controller history, counters and
status (`State`), so a sample's result does not depend on what else is in the batch, and a
sample that fails is frozen and marked while the others go on.

- One host sync per step: the "anyone still running?" flag and the number of outputs to
  write travel together in one `.tolist()`.
- Dense output uses the method's free interpolant (`dense.py`), so steps are never
  shortened to hit output times.
- The step-size controller (`controller.py`) works on detached tensors: gradients flow
  through the stages and the interpolant, not through the step-size choice (a prototype
  that let r^(−1/5) into autograd produced NaN gradients near r = 0). It owns the error
  test's tolerances; `Problem` (`problem.py`) holds it with the rest of the solve's
  settings, and `Constants` what the step reads of them.
- Two ways through a step, with the same forward: eagerly (the default), the stages are
  `fused.py`'s autograd nodes, whose backward is written for the tableau, and the step's end
  (`fused.end_step`) selects the next state and writes the outputs it crossed into one
  buffer; compiled, or with `fused=False`, `attempt_step` records every op on autograd's
  tape, which `torch.compile` takes whole (`STEP`: dynamo cannot trace the fused nodes'
  shared buffers), and the outputs are gathered once at the end. The loop around either
  does the host-side work.
- With `solve(..., checkpoints=C)` each step (`loop_step`) runs through
  `checkpoint.Checkpointed`: one autograd node that keeps nothing, rerun in the backward
  pass from a kept state (`replica`: the reruns write their outputs apart).
- For compaction (`solve(..., restrict=...)`) the loop may stop once few samples still run,
  returning each sample's `State` (`Restart`), from which `solve` goes on with those
  samples only: a restart needs no change to either step.
"""

from __future__ import annotations

import copy
import math
from functools import partial
from typing import NamedTuple

import torch

from mpnode_cli.solver.checkpoint import Checkpointed
from mpnode_cli.solver.compile_cache import CompileCache
from mpnode_cli.solver.controller import StepController
from mpnode_cli.solver.dense import (
    OutputTimes,
    dense_weights,
    gather_outputs,
    host_lanes,
    lanes,
    on_host,
)
from mpnode_cli.solver.fused import StepTape, collect_outputs, end_step, fused_stages, start_outputs
from mpnode_cli.solver.problem import Problem
from mpnode_cli.solver.runge_kutta import RHS, Stages, StageTableau, rk_step
from mpnode_cli.solver.solution import Status

# After this many consecutive rejections for a non-finite error estimate (the step shrinks by
# 5× each time, so by ~1e14 in all) the right-hand side itself is taken to be non-finite.
_MAX_NON_FINITE_REJECTS = 20


class State(NamedTuple):
    """Each sample's place in the solve; `[B]` tensors unless marked. Tensors only, so
    that the compiled step takes and returns it as graph inputs and outputs."""

    t: torch.Tensor  # float64 time reached
    dt: torch.Tensor  # float64 size of the next step to try
    y: torch.Tensor  # [B, F] state at t
    k1: torch.Tensor  # [B, F] f(t, y)
    running: torch.Tensor  # bool: neither finished nor failed
    stop_idx: torch.Tensor  # int64 index of the next stop
    stop_t: torch.Tensor  # float64 time of the next stop, which no step crosses
    err_prev: torch.Tensor  # float64 controller history
    n_steps: torch.Tensor  # int64 attempted steps
    n_accepted: torch.Tensor  # int64 accepted steps
    n_nonfinite: torch.Tensor  # int64 consecutive rejections for NaN/inf
    out_idx: torch.Tensor  # int64 index of the next output to fill


class Constants(NamedTuple):
    """What every step of one solve reads (of its `Problem`, and the buffers it made);
    a NamedTuple, which the compiled step takes as it is."""

    tab: StageTableau
    ctrl: StepController  # with the error test's tolerances
    order: int  # p, the error estimate's order + 1 (the controller's exponents' divisor)
    stages: Stages | None  # the recorded step's stage buffer (None: fused steps)
    tape: StepTape | None  # the fused steps' buffers (None: recorded steps)
    ts: torch.Tensor  # [T] float64 output times
    stops_pad: torch.Tensor  # [S + 1] float64 stops, the last repeated
    n_stops: int
    max_steps: int
    block: int = 0  # compaction's block of samples kept or dropped together (0: no count)


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


class Attempt(NamedTuple):
    """What the loop needs of one attempted step besides the next `State`; `[B]` tensors."""

    jumped: torch.Tensor  # bool: landed on an interior stop (f may change there)
    n_cross: torch.Tensor  # int64 outputs the accepted step crossed
    failed: torch.Tensor  # bool: failed at this step
    too_many: torch.Tensor  # bool: too many non-finite rejections in a row
    underflow: torch.Tensor  # bool: the next step would not move the clock
    accept: torch.Tensor  # bool: the step was accepted
    t: torch.Tensor  # float64 step start
    h: torch.Tensor  # float64 step size
    y: torch.Tensor  # [B, F] state at the step start
    hk: torch.Tensor | None = None  # [s, B, F] the stages h·k_i (recorded steps)
    f_new: torch.Tensor | None = None  # [B, *S] f at the new state (fused steps)
    rec: object = None  # the fused step's `TapeRecord`, which `end_step` finishes


def _rms(x: torch.Tensor) -> torch.Tensor:
    """`[B, F]` → `[B]` root mean square over each row, in float64 (the norm itself in
    x's dtype)."""
    return torch.linalg.vector_norm(x, dim=1).double() / math.sqrt(x.shape[1])


def initial_step(fun: RHS, t0: torch.Tensor, y: torch.Tensor, k1: torch.Tensor,
                 ctrl: StepController, span: torch.Tensor, p: int) -> torch.Tensor:
    """Hairer, Nørsett & Wanner, Solving ODEs I, §II.4: a first step size per sample.

    Args:
        fun: the right-hand side on flat states; t0: `[B]` float64 start times;
        y: `[B, F]` states there; k1: `[B, F]` f(t0, y); ctrl: its `scale` weighs y;
        span: `[B]` float64 the time span; p: the error estimate's order + 1 (5 for a 5(4)
            pair), as in Hairer's DOPRI5 (`IORD`).

    Returns:
        `[B]` float64 step sizes, finite and positive.
    """
    with torch.no_grad():
        scale = ctrl.scale(y)
        d0, d1 = _rms(y / scale), _rms(k1 / scale)
        h0 = torch.where((d0 < 1e-5) | (d1 < 1e-5), 1e-6, 0.01 * d0 / d1.clamp(1e-300))
        h0 = torch.minimum(h0, span)
        y1 = y + h0.to(y.dtype)[:, None] * k1
        f1 = fun(t0 + h0, y1)
        d2 = _rms((f1 - k1) / scale) / h0
        dmax = torch.maximum(d1, d2)
        # A tensor numerator: torch's `0.01 / x` is 0.01 · (1/x), rounded twice.
        h1 = torch.where(dmax <= 1e-15, (h0 * 1e-3).clamp(1e-6),
                         torch.pow(torch.full_like(dmax, 0.01) / dmax.clamp(1e-300), 1.0 / p))
        h = torch.minimum(torch.minimum(100 * h0, h1), span)
        return torch.where((h > 0) & (h < math.inf), h, span * 1e-6)  # finite and > 0


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
    host = on_host(y.device, problem.compile)
    stages = tape = None
    if problem.fused and not problem.compile:
        tape = StepTape(tab, y, problem.batch_shape(batch), record, problem.ts.numel(), host)
        start_outputs(tape, y)
        steps = FusedSteps(tape, problem.ts, shaped, host)
    else:
        stages = Stages(tab.stages, batch, y.shape[1], y, not record)
        steps = RecordedSteps(y, problem.ts, tab, host, host and not record)
    consts = Constants(tab, problem.controller, problem.order, stages, tape, problem.ts,
                       stops_pad, problem.stops.numel(), problem.max_steps, problem.block)
    # Stop for compaction when few enough rows still run and enough could be dropped.
    keep_max = (min(int(batch * COMPACT_KEEP_FRACTION), batch - COMPACT_MIN_DROP)
                if problem.block else -1)
    step = partial(loop_step, fun, consts, problem.compile, steps)
    if problem.checkpoints is not None and record:  # steps recomputed in the backward pass
        step = Checkpointed(step, problem.checkpoints, lambda: partial(
            loop_step, fun, consts, False, steps.replica()))
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


def loop_step(fun, consts, compile, steps, carry):
    """One attempted step of the samples that run, and its bookkeeping: `carry` is
    `(state, status, n_f)`; returns the next carry and the step's `control` flags as
    Python ints (its one host sync). What `checkpoint.Checkpointed` reruns."""
    state, status, n_f = carry
    state, flags, step = steps.attempt(fun, consts, state, compile)
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


def plan_step(state: State):
    """`(h, t_new, land)`, each `[B]`: the step to attempt, clipped so as not to cross the
    next stop (0 for a sample that does not run), where it ends, and whether it lands on
    the stop."""
    with torch.no_grad():
        to_stop = state.stop_t - state.t
        land = state.dt >= to_stop
        h = torch.where(state.running, torch.minimum(state.dt, to_stop), 0.0)
        t_new = torch.where(land, state.stop_t, state.t + h)
    return h, t_new, land


def control(consts: Constants, state: State, h, t_new, land, y_new, err):
    """Error control and bookkeeping of an attempted step, outside autograd.

    Returns:
        `(state, flags, attempt)`: the next `State` with `y` and `k1` still the step's start
        (the caller advances them); `flags`, a `[4]` int64 tensor (anyone still running,
        the most outputs one sample crossed, anyone landed on an interior stop, anyone
        failed; with `consts.block`, a fifth: the rows of the blocks still running), read
        by the loop in its one sync; and the `Attempt`.
    """
    ctrl, running = consts.ctrl, state.running
    with torch.no_grad():
        r = _rms(err / ctrl.scale(state.y, y_new))
        finite = r < math.inf  # r ≥ 0, so this is isfinite in one op instead of three
        r = ctrl.ratio(r, finite)
        accept = running & (r <= 1.0)
        dt_next, err_prev = ctrl.propose(h, r, state.err_prev, accept, consts.order)
        landed = accept & land
        # A step clipped at a stop says little about the step size the solution allows:
        # keep the proposal it was clipped from.
        dt_next = torch.where(landed, torch.maximum(dt_next, state.dt), dt_next)
        dt = torch.where(running, dt_next, state.dt)

        n_cross = torch.where(
            accept, torch.searchsorted(consts.ts, t_new, right=True) - state.out_idx, 0)
        n_steps = state.n_steps + running
        stop_idx = state.stop_idx + landed
        n_nonfinite = torch.where(finite, 0, state.n_nonfinite + running)
        live = running & (stop_idx < consts.n_stops)
        too_many = n_nonfinite >= _MAX_NON_FINITE_REJECTS
        # The next step would not move the clock. Checked after accepted steps too: near a
        # blow-up the step shrinks geometrically while every step is accepted, and checking
        # only rejections let such a sample take thousands of steps that advance no time.
        t_next = torch.where(accept, t_new, state.t)
        underflow = t_next + dt <= t_next
        failed = (too_many | underflow | (n_steps >= consts.max_steps)) & live
        running_next = live ^ failed  # failed ⊆ live
        # Landing on an interior stop invalidates FSAL: f may change there (a new control).
        jumped = landed & live
        flags = _flags(running_next, n_cross, jumped, failed, *_kept(running_next, consts.block))
    step = Attempt(jumped, n_cross, failed, too_many, underflow, accept, state.t, h, state.y)
    state = State(t_next, dt, state.y, state.k1, running_next, stop_idx,
                  torch.take(consts.stops_pad, stop_idx), err_prev, n_steps,
                  state.n_accepted + accept, n_nonfinite, state.out_idx)
    return state, flags, step


def _kept(running: torch.Tensor, block: int) -> tuple[torch.Tensor, ...]:
    """The rows of the blocks that still run, for compaction (none without a block)."""
    if not block:
        return ()
    return (running.sum() if block == 1 else running.reshape(-1, block).any(1).sum() * block),


def _flags(*xs: torch.Tensor) -> torch.Tensor:
    """One int64 tensor of each `[B]` tensor's max (a bool's any) and any scalars after
    them: what the loop reads in its one sync (`.tolist()`)."""
    # One stack and one amax (type promotion makes the bools 0/1), against a reduction
    # per vector and a stack of their results.
    vectors = [x for x in xs if x.ndim]
    flags = torch.stack(vectors).amax(1)
    scalars = [x.view(1) for x in xs if not x.ndim]
    return torch.cat([flags, *scalars]) if scalars else flags


def attempt_step(fun: RHS, consts: Constants, state: State):
    """Attempt one step for every running sample, every op recorded by autograd; pure
    tensor code, no host sync (what `STEP` compiles).

    Returns:
        `(state, flags, attempt)` as `control`'s, with the state advanced: an accepted
        sample moves to the new state; FSAL, the last stage is f there.
    """
    h, t_new, land = plan_step(state)
    y_new, err, f_new, hk = rk_step(fun, consts.tab, consts.stages, state.t, h, state.y,
                                    state.k1, t_new)
    state_next, flags, step = control(consts, state, h, t_new, land, y_new, err)
    acc2 = step.accept[:, None]
    state_next = state_next._replace(y=torch.where(acc2, y_new, state.y),
                                     k1=torch.where(acc2, f_new, state.k1))
    return state_next, flags, step._replace(hk=hk)


STEP = CompileCache(attempt_step)  # the step, compiled once per process when asked


class RecordedSteps:
    """Steps recorded op by op (`attempt_step`, compiled or not), and their outputs:
    `(column index [B, W], value [B, W, F])` per writing step, scattered into the result
    once at the end (one gather in the backward pass instead of one full-size copy per
    step); a spare column at index T takes the writes of masked-out lanes."""

    def __init__(self, y: torch.Tensor, ts: torch.Tensor, tab: StageTableau,
                 host_weights: bool, host_sums: bool):
        """`host_weights`, `host_sums`: the dense output's weights and its (untracked)
        sums in numpy (`dense.py`)."""
        self.n_out, self.out = ts.numel(), OutputTimes.of(ts, tab, host_weights)
        self.sums = host_lanes if host_sums else lanes
        self.cols = [torch.zeros(y.shape[0], 1, dtype=torch.long, device=y.device)]
        self.vals = [y.unsqueeze(1)]

    @staticmethod
    def attempt(fun: RHS, consts: Constants, state: State, compile: bool):
        return STEP(compile, fun, consts, state)

    def end(self, state: State, step: Attempt, width: int) -> State:
        """Collect the outputs the step crossed (the step has advanced the state)."""
        if width > 0:
            cols, valid, coef = dense_weights(self.out, step.t, step.h, state.out_idx,
                                              step.n_cross, width)
            coef = coef.to(step.y.dtype)
            self.cols.append(torch.where(valid, cols, self.n_out))
            self.vals.append(self.sums(coef, step.hk, step.y))
        return state

    def result(self, y0: torch.Tensor, state: State) -> torch.Tensor:
        """`[B, T, F]` the outputs, NaN where none was written."""
        return gather_outputs(self.cols, self.vals, self.n_out)


class FusedSteps:
    """Steps whose stages are `fused.py`'s autograd nodes; each step's end writes the
    outputs it crossed into the tape's output buffer."""

    def __init__(self, tape: StepTape, ts: torch.Tensor, shaped: RHS, host_weights: bool):
        batch, dev = tape.shape[0], ts.device
        self.tape, self.shaped = tape, shaped
        self.out = OutputTimes.of(ts, tape.tab, host_weights)
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

    def attempt(self, fun: RHS, consts: Constants, state: State, compile: bool):
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
