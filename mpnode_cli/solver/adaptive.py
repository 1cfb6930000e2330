"""The adaptive loop: per-sample step sizes under error control, with dense output.

Each sample has its own time, step size, error control, controller history, counters and
status (`State`), so a sample's result does not depend on what else is in the batch, and a
sample that fails is frozen and marked while the others go on.

- One host sync per step: the "anyone still running?" flag and the number of outputs to
  write travel together in one `.tolist()`.
- Dense output uses the method's free interpolant, so steps are never shortened to hit
  output times; the outputs crossed by a step are written with a bounded, static-shape
  scatter (no `nonzero`).
- The step-size controller (`controller.py`) works on detached arrays: gradients flow
  through the stages and the interpolant, not through the step-size choice (a prototype
  that let r^(−1/5) into autograd produced NaN gradients near r = 0).
- The step's small arithmetic on `[B]` vectors (`plan_step`, `control`, `dense_weights`,
  `initial_step`) is written once against an array namespace (`host.py`): numpy views of
  the tensors in an uncompiled CPU solve, where a torch op that small costs several times
  a numpy op, and torch on CUDA and under `compile`. Both take the same steps bit for bit;
  the `State` holds tensors either way.
- Two ways through a step, with the same forward: eagerly (the default), the stages are
  `fused.py`'s autograd nodes, whose backward is written for the tableau, and the step's end
  (`fused.end_step`) selects the next state and writes the outputs it crossed into one
  buffer; compiled, or with `fused=False`, `attempt_step` records every op on autograd's
  tape, which `torch.compile` takes whole (`STEP`: dynamo cannot trace the fused nodes'
  shared buffers), and the outputs are gathered once at the end. The loop around either
  does the host-side work.
- For compaction (`solve(..., restrict=...)`) the loop may stop once few samples still run,
  returning each sample's `State` (`Restart`), from which `solve` goes on with those
  samples only: a restart needs no change to either step.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import NamedTuple

import torch

from mpnode_cli.solver.compile_cache import CompileCache
from mpnode_cli.solver.controller import StepController
from mpnode_cli.solver.fused import StepTape, collect_outputs, end_step, fused_stages, start_outputs
from mpnode_cli.solver.host import Ops, TorchOps, ops_for
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
    """What every step of one solve shares."""

    tab: StageTableau
    ctrl: StepController
    stages: Stages | None  # the recorded step's stage buffer (None: fused steps)
    tape: StepTape | None  # the fused steps' buffers (None: recorded steps)
    ts: object  # [T] float64 output times, an array of `ops`
    stops_pad: object  # [S + 1] float64 stops, the last repeated, an array of `ops`
    n_stops: int
    rtol: float
    atol: float
    max_steps: int
    block: int = 0  # compaction's block of samples kept or dropped together (0: no count)
    ops: Ops = TorchOps  # the namespace of the step's small arithmetic (`host.py`)


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
    rec: object = None  # the fused step's `StepRecord`, which `end_step` finishes


def initial_step(fun, t0, y, k1, rtol, atol, span, p, xp: Ops = TorchOps):
    """Hairer, Nørsett & Wanner, Solving ODEs I, §II.4: a first step size per sample.

    p: the error estimate's order + 1 (5 for a 5(4) pair), as in Hairer's DOPRI5 (`IORD`);
    xp: the namespace of the arithmetic (`host.py`), f's own in torch.
    """
    t0, y, k1, span = xp.arrays(t0, y, k1, span)
    with torch.no_grad():
        scale = atol + rtol * abs(y)
        d0, d1 = xp.rms(y / scale), xp.rms(k1 / scale)
        h0 = xp.where((d0 < 1e-5) | (d1 < 1e-5), 1e-6, 0.01 * d0 / xp.clip(d1, 1e-300))
        h0 = xp.minimum(h0, span)
        y1 = y + xp.astype(h0, y)[:, None] * k1
        f1, = xp.arrays(fun(*xp.tensors(t0 + h0, y1)))
        d2 = xp.rms((f1 - k1) / scale) / h0
        dmax = xp.maximum(d1, d2)
        h1 = xp.where(
            dmax <= 1e-15,
            xp.clip(h0 * 1e-3, 1e-6),
            xp.pow(0.01 / xp.clip(dmax, 1e-300), 1.0 / p),
        )
        h = xp.minimum(xp.minimum(100 * h0, h1), span)
        h = xp.where((h > 0) & (h < math.inf), h, span * 1e-6)  # finite and > 0
    return xp.tensors(h)[0]


def solve_adaptive(fun: RHS, tab: StageTableau, p: int, ctrl: StepController,
                   y: torch.Tensor, ts: torch.Tensor, stops: torch.Tensor, rtol: float,
                   atol: float, dt0, max_steps: int, compile: bool = False,
                   report: Callable[[torch.Tensor], None] | None = None,
                   shaped: RHS | None = None, shape: tuple[int, ...] | None = None,
                   start: Restart | None = None, block: int = 0):
    """Integrate with adaptive steps.

    Args:
        fun: the right-hand side on flat states, `fun(t [B], y [B, F]) -> [B, F]`.
        p: the error estimate's order + 1 (for the first step size; `ctrl` has its own).
        y: `[B, F]` initial states at `ts[0]`; ts: `[T]` float64 output times;
        stops: sorted float64 times in (t0, t_end] that steps land on, t_end last.
        dt0: the first step size, scalar or `[B]`, or None for `initial_step`'s.
        compile: run `attempt_step` compiled (`STEP`).
        report: called with each sample's time `[B]` after every step.
        shaped: the right-hand side on `[B, *S]` states (`shape`), for fused steps; None
            records every op of the step instead (`attempt_step`, as compiled).
        start: go on from where an earlier solve of these samples stopped (its `Restart`,
            the samples selected) instead of starting at `ts[0]`; `y` is then its `state.y`.
        block: stop early for compaction, once the samples still running, counted in whole
            blocks of `block` consecutive samples, make at most half of the batch and at
            least `COMPACT_MIN_DROP` rows could be dropped (0: run to the end). The caller
            passes a block that divides the batch, and 0 when compiled
            (`solve._compaction_block`).
        The rest are `solve`'s.

    Returns:
        `(ys [B, T, F], status [B], stats, restart)`, the first three as `solve` returns
        them, and `restart`, None where the solve ran to the end; else it stopped early
        (`block`): outputs beyond a running sample's progress are NaN and its stats are
        those so far, and `restart` says where to go on from.
    """
    batch = y.shape[0]
    dev, f64 = y.device, torch.float64
    n_out = ts.numel()
    t0 = ts[0]
    xp = ops_for(dev, compile)

    stops_pad = torch.cat([stops, stops[-1:]])  # finished samples index one past the end
    if start is not None:
        state, status, n_f = start
    else:
        t = t0.expand(batch).clone()  # (B,) float64
        k1 = fun(t, y)
        n_f = torch.ones(batch, dtype=torch.long, device=dev)
        span = (ts[-1] - t0).expand(batch)
        if dt0 is None:
            dt = initial_step(fun, t, y, k1, rtol, atol, span, p, xp)
            n_f += 1
        else:
            dt = torch.as_tensor(dt0, dtype=f64, device=dev).expand(batch).clone()

        stop_idx = torch.zeros(batch, dtype=torch.long, device=dev)
        start_ok = torch.isfinite(k1).all(dim=1) & torch.isfinite(y).all(dim=1)
        status = torch.where(start_ok, Status.SUCCESS, Status.NON_FINITE)
        state = State(
            t=t, dt=dt, y=y, k1=k1, running=start_ok, stop_idx=stop_idx,
            stop_t=stops_pad[stop_idx],
            err_prev=torch.full((batch,), ctrl.initial_history(), dtype=f64, device=dev),
            n_steps=torch.zeros_like(stop_idx), n_accepted=torch.zeros_like(stop_idx),
            n_nonfinite=torch.zeros_like(stop_idx),
            out_idx=torch.ones(batch, dtype=torch.long, device=dev))
    k1 = state.k1
    record = torch.is_grad_enabled() and (k1.requires_grad or y.requires_grad)
    fused = shaped is not None and not compile
    ts_xp, stops_xp = xp.arrays(ts, stops_pad)
    # The dense outputs' sums in numpy only where autograd does not record the step: the
    # recorded step (`fused=False`) needs torch's to differentiate, and the two kinds of
    # step agree bit for bit.
    lanes = TorchOps if record else xp
    if fused:
        tape = StepTape(tab, y, shape, record, n_out, lanes)
        start_outputs(tape, y)
        consts = Constants(tab, ctrl, None, tape, ts_xp, stops_xp, stops.numel(), rtol, atol,
                           max_steps, block, xp)
        steps = FusedSteps(tape, ts, shaped, xp)
    else:
        consts = Constants(tab, ctrl, Stages(tab.stages, batch, y.shape[1], y, not record),
                           None, ts_xp, stops_xp, stops.numel(), rtol, atol, max_steps, block,
                           xp)
        steps = RecordedSteps(y, ts, tab, xp, lanes)
    # Stop for compaction when few enough rows still run and enough could be dropped.
    keep_max = (min(int(batch * COMPACT_KEEP_FRACTION), batch - COMPACT_MIN_DROP) if block
                else -1)
    state, status, n_f, early = _loop(fun, consts, state, status, n_f, steps, compile,
                                      report, keep_max)
    stats = {"n_steps": state.n_steps, "n_accepted": state.n_accepted,
             "n_rejected": state.n_steps - state.n_accepted,
             "n_f_evals": n_f + (tab.stages - 1) * state.n_steps}
    return steps.result(y, state), status, stats, Restart(state, status, n_f) if early else None


# Compaction stops a solve only when at least this many rows would be dropped (restarting
# a few rows costs more than it saves), and at most this fraction of its rows still run.
COMPACT_MIN_DROP = 8
COMPACT_KEEP_FRACTION = 0.5


def _loop(fun, consts, state, status, n_f, steps, compile, report, keep_max):
    """Step until no sample runs, or (`keep_max` ≥ 0, `consts.block`) until the rows of
    the blocks that still run are at most `keep_max`; returns `(state, status, n_f,
    stopped early)`."""
    while True:
        state, flags, step = steps.attempt(fun, consts, state, compile)
        flags = flags.tolist()  # the step's one sync
        any_running, width, any_jumped, any_failed = flags[:4]
        if any_failed:  # rare: record why those samples stopped
            why = torch.where(step.too_many, Status.NON_FINITE,
                              torch.where(step.underflow, Status.DT_UNDERFLOW,
                                          Status.MAX_STEPS))
            status = torch.where(step.failed, why, status)
        state = steps.end(state, step, width)
        if width > 0:
            state = state._replace(out_idx=state.out_idx + step.n_cross)
        if any_jumped:  # right-limit derivative at the stop, for those that landed there
            k1 = torch.where(step.jumped[:, None], fun(state.t, state.y), state.k1)
            n_f = n_f + state.running
            state = state._replace(k1=k1)
        if not any_running:
            return state, status, n_f, False
        if consts.block and flags[4] <= keep_max:
            return state, status, n_f, True
        if report is not None:
            report(state.t)


def plan_step(consts: Constants, state: State):
    """`(h, t_new, land)`, each `[B]`: the step to attempt, clipped so as not to cross the
    next stop (0 for a sample that does not run), where it ends, and whether it lands on
    the stop."""
    xp = consts.ops
    t, dt, running, stop_t = xp.arrays(state.t, state.dt, state.running, state.stop_t)
    with xp.no_grad():
        to_stop = stop_t - t
        land = dt >= to_stop
        h = xp.where(running, xp.minimum(dt, to_stop), 0.0)
        t_new = xp.where(land, stop_t, t + h)
    return xp.tensors(h, t_new, land)


def control(consts: Constants, state: State, h, t_new, land, y_new, err):
    """Error control and bookkeeping of an attempted step, outside autograd, in the
    solve's namespace (`consts.ops`).

    Returns:
        `(state, flags, attempt)`: the next `State` with `y` and `k1` still the step's start
        (the caller advances them); `flags`, a `[4]` int64 array (anyone still running, the
        most outputs one sample crossed, anyone landed on an interior stop, anyone failed;
        with `consts.block`, a fifth: the rows of the blocks still running), read by the
        loop in its one sync (a tensor in torch; in numpy, host values already); and the
        `Attempt`.
    """
    _, ctrl, _, _, ts, stops_pad, n_stops, rtol, atol, max_steps, block, xp = consts
    t, dt, running, stop_idx, err_prev, n_steps, n_acc, n_nonfinite, out_idx = xp.arrays(
        state.t, state.dt, state.running, state.stop_idx, state.err_prev, state.n_steps,
        state.n_accepted, state.n_nonfinite, state.out_idx)
    h_step = h  # the tensor, for the `Attempt`
    h, t_new, land, y, y_new, err = xp.arrays(h, t_new, land, state.y, y_new, err)
    with xp.no_grad():
        scale = xp.maximum(abs(y), abs(y_new))
        scale *= rtol
        scale += atol
        r = xp.rms(err / scale)
        finite = r < math.inf  # r ≥ 0, so this is isfinite in one op instead of three
        r = ctrl.ratio(r, finite, xp)
        accept = running & (r <= 1.0)
        dt_next, err_prev = ctrl.propose(h, r, err_prev, accept, xp)
        landed = accept & land
        # A step clipped at a stop says little about the step size the solution allows:
        # keep the proposal it was clipped from.
        dt_next = xp.where(landed, xp.maximum(dt_next, dt), dt_next)
        dt = xp.where(running, dt_next, dt)

        n_cross = xp.where(accept, xp.searchsorted(ts, t_new) - out_idx, 0)
        n_steps = n_steps + running
        n_acc = n_acc + accept
        stop_idx = stop_idx + landed
        stop_t = xp.take(stops_pad, stop_idx)
        n_nonfinite = xp.where(finite, 0, n_nonfinite + running)
        live = running & (stop_idx < n_stops)
        too_many = n_nonfinite >= _MAX_NON_FINITE_REJECTS
        # The next step would not move the clock. Checked after accepted steps too: near a
        # blow-up the step shrinks geometrically while every step is accepted, and checking
        # only rejections let such a sample take thousands of steps that advance no time.
        t_next = xp.where(accept, t_new, t)
        underflow = t_next + dt <= t_next
        failed = (too_many | underflow | (n_steps >= max_steps)) & live
        running_next = live ^ failed  # failed ⊆ live
        # Landing on an interior stop invalidates FSAL: f may change there (a new control).
        jumped = landed & live
        kept = ()
        if block:  # the rows of the blocks that still run, for compaction
            kept = (running_next.sum() if block == 1 else
                    running_next.reshape(-1, block).any(1).sum() * block),
        flags = xp.flags(running_next, n_cross, jumped, failed, *kept)
    step = Attempt(*xp.tensors(jumped, n_cross, failed, too_many, underflow, accept), state.t,
                   h_step, state.y)
    state = State(*xp.tensors(t_next, dt), state.y, state.k1,
                  *xp.tensors(running_next, stop_idx, stop_t, err_prev, n_steps, n_acc,
                              n_nonfinite), state.out_idx)
    return state, flags, step


def attempt_step(fun: RHS, consts: Constants, state: State):
    """Attempt one step for every running sample, every op recorded by autograd; pure
    tensor code, no host sync (what `STEP` compiles).

    Returns:
        `(state, flags, attempt)` as `control`'s, with the state advanced: an accepted
        sample moves to the new state; FSAL, the last stage is f there.
    """
    h, t_new, land = plan_step(consts, state)
    y_new, err, f_new, hk = rk_step(fun, consts.tab, consts.stages, state.t, h, state.y,
                                    state.k1, t_new)
    state_next, flags, step = control(consts, state, h, t_new, land, y_new, err)
    acc2 = step.accept[:, None]
    state_next = state_next._replace(y=torch.where(acc2, y_new, state.y),
                                     k1=torch.where(acc2, f_new, state.k1))
    return state_next, flags, step._replace(hk=hk)


STEP = CompileCache(attempt_step)  # the step, compiled once per process when asked


class OutputTimes(NamedTuple):
    """What dense output needs of a solve, as arrays of its namespace `ops`."""

    ops: Ops
    ts: object  # [T] float64 output times
    arange: object  # [T] int64 0, 1, ..., T − 1
    interp_t: object  # [s, K] float64 the interpolant's coefficients (`StageTableau`)

    @classmethod
    def of(cls, ts: torch.Tensor, tab: StageTableau, xp: Ops) -> OutputTimes:
        return cls(xp, *xp.arrays(ts, torch.arange(ts.numel(), device=ts.device),
                                  tab.interp_t))


def dense_weights(out: OutputTimes, step: Attempt, out_idx: torch.Tensor, width: int):
    """The interpolant's weights at the ≤ `width` output times each sample's step crossed.

    Returns:
        `(cols [B, W], valid [B, W], coef [B, W, s])`, arrays of `out.ops`: lane `w` of
        sample `b` belongs in output column `cols[b, w] = out_idx[b] + w` where `valid`
        (`w < n_cross[b]`), and is y + Σ_i coef[b, w, i]·h·k_i, coef (float64) the b_i(θ)
        of its time.
    """
    xp, ts = out.ops, out.ts
    out_idx, n_cross, t, h = xp.arrays(out_idx, step.n_cross, step.t, step.h)
    w = out.arange[:width]
    cols = out_idx[:, None] + w  # (B, W)
    valid = w < n_cross[:, None]
    with xp.no_grad():
        h_safe = xp.where(h > 0, h, 1.0)
        theta = (xp.take(ts, xp.clip(cols, None, ts.shape[0] - 1)) - t[:, None]) / h_safe[:, None]
        theta = xp.clip(theta, 0.0, 1.0)  # (B, W)
        coef = xp.interpolant(theta, out.interp_t)  # (B, W, s): b_i(θ)
    return cols, valid, coef


class RecordedSteps:
    """Steps recorded op by op (`attempt_step`, compiled or not), and their outputs:
    `(column index [B, W], value [B, W, F])` per writing step, scattered into the result
    once at the end (one gather in the backward pass instead of one full-size copy per
    step); a spare column at index T takes the writes of masked-out lanes."""

    def __init__(self, y: torch.Tensor, ts: torch.Tensor, tab: StageTableau, xp: Ops,
                 lanes: Ops):
        self.n_out, self.out, self.lanes = ts.numel(), OutputTimes.of(ts, tab, xp), lanes
        self.cols = [torch.zeros(y.shape[0], 1, dtype=torch.long, device=y.device)]
        self.vals = [y.unsqueeze(1)]

    @staticmethod
    def attempt(fun: RHS, consts: Constants, state: State, compile: bool):
        return STEP(compile, fun, consts, state)

    def end(self, state: State, step: Attempt, width: int) -> State:
        """Collect the outputs the step crossed (the step has advanced the state)."""
        if width > 0:
            cols, valid, coef = self.out.ops.tensors(*dense_weights(self.out, step,
                                                                    state.out_idx, width))
            coef = coef.to(step.y.dtype)
            self.cols.append(torch.where(valid, cols, self.n_out))
            self.vals.append(self.lanes.lanes(coef, step.hk, step.y))
        return state

    def result(self, y0: torch.Tensor, state: State) -> torch.Tensor:
        """`[B, T, F]` the outputs, NaN where none was written."""
        return gather_outputs(self.cols, self.vals, self.n_out)


class FusedSteps:
    """Steps whose stages are `fused.py`'s autograd nodes; each step's end writes the
    outputs it crossed into the tape's output buffer."""

    def __init__(self, tape: StepTape, ts: torch.Tensor, shaped: RHS, xp: Ops):
        batch, dev = tape.shape[0], ts.device
        self.tape, self.shaped, self.out = tape, shaped, OutputTimes.of(ts, tape.tab, xp)
        # (B, 1) each sample's row of column 0 in the output buffer, an array of `xp`
        self.base, = xp.arrays(torch.arange(batch, device=dev)[:, None] * ts.numel())
        self.spare = batch * ts.numel()  # the output buffer's spare row

    def attempt(self, fun: RHS, consts: Constants, state: State, compile: bool):
        """`control`'s `(state, flags, attempt)`; `end` then advances y and k₁."""
        h, t_new, land = plan_step(consts, state)
        rec, y_new, err, f_new = fused_stages(self.shaped, consts.tab, self.tape, state.t, h,
                                              state.y, state.k1, t_new)
        state, flags, step = control(consts, state, h, t_new, land, y_new, err)
        return state, flags, step._replace(f_new=f_new, rec=rec)

    def end(self, state: State, step: Attempt, width: int) -> State:
        """Advance the accepted samples and write the outputs the step crossed."""
        rows = coef = None
        if width > 0:
            xp = self.out.ops
            cols, valid, coef = dense_weights(self.out, step, state.out_idx, width)
            rows = xp.where(valid, self.base + cols, self.spare).reshape(-1)  # (B·W,)
            rows, coef = xp.tensors(rows, coef)
        y, k1 = end_step(step.rec, step.f_new, step.accept, rows, coef)
        return state._replace(y=y, k1=k1)

    def result(self, y0: torch.Tensor, state: State) -> torch.Tensor:
        """`[B, T, F]` the outputs, NaN where none was written."""
        return collect_outputs(self.tape, y0, state.y, state.k1)


def gather_outputs(cols: list[torch.Tensor], vals: list[torch.Tensor], n_out: int):
    """`[B, T, F]` outputs from the steps' `(cols [B, W], values [B, W, F])`, NaN where none.

    Whole rows are copied into a flat `[B·T + B·L, F]` buffer (`index_copy`, whose backward
    is one `index_select`); each masked-out lane gets a row of its own past `B·T`, so no
    index repeats.
    """
    cols_all = torch.cat(cols, dim=1)  # (B, L)
    vals_all = torch.cat(vals, dim=1)  # (B, L, F)
    batch, lanes, feat = vals_all.shape
    dev = cols_all.device
    rows = torch.arange(batch, device=dev)[:, None] * n_out + cols_all
    spare = batch * n_out + torch.arange(batch * lanes, device=dev).view(batch, lanes)
    rows = torch.where(cols_all < n_out, rows, spare).reshape(-1)
    out = torch.full((batch * (n_out + lanes), feat), math.nan, dtype=vals_all.dtype,
                     device=dev)
    out = out.index_copy(0, rows, vals_all.reshape(batch * lanes, feat))
    return out[: batch * n_out].view(batch, n_out, feat)
