"""The adaptive loop: per-sample step sizes under error control, with dense output.

Each sample has its own time, step size, error control, controller history, counters and
status (`State`), so a sample's result does not depend on what else is in the batch, and a
sample that fails is frozen and marked while the others go on.

- One host sync per step: the "anyone still running?" flag and the number of outputs to
  write travel together in one `.tolist()`.
- Dense output uses the method's free interpolant, so steps are never shortened to hit
  output times; the outputs crossed by a step are written with a bounded, static-shape
  scatter (no `nonzero`).
- The step-size controller (`controller.py`) works on detached tensors: gradients flow
  through the stages and the interpolant, not through the step-size choice (a prototype
  that let r^(−1/5) into autograd produced NaN gradients near r = 0).
- `attempt_step` is pure tensor code over `State`, so that `torch.compile` can take it
  whole (`STEP`); the loop around it does the host-side work.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import NamedTuple

import torch

from mpnode_cli.solver.compile_cache import CompileCache
from mpnode_cli.solver.controller import StepController
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
    stages: Stages
    ts: torch.Tensor  # [T] float64 output times
    stops_pad: torch.Tensor  # [S + 1] float64 stops, the last repeated
    n_stops: int
    rtol: float
    atol: float
    max_steps: int


class Attempt(NamedTuple):
    """What the loop needs of one attempted step besides the next `State`; `[B]` tensors."""

    jumped: torch.Tensor  # bool: landed on an interior stop (f may change there)
    n_cross: torch.Tensor  # int64 outputs the accepted step crossed
    failed: torch.Tensor  # bool: failed at this step
    too_many: torch.Tensor  # bool: too many non-finite rejections in a row
    underflow: torch.Tensor  # bool: the next step would not move the clock
    t: torch.Tensor  # float64 step start
    h: torch.Tensor  # float64 step size
    y: torch.Tensor  # [B, F] state at the step start
    hk: torch.Tensor  # [s, B, F] the stages h·k_i


def rms(x: torch.Tensor) -> torch.Tensor:
    """`[B, F]` → `[B]` root mean square over each sample's elements, in float64."""
    return torch.linalg.vector_norm(x, dim=1).double() / math.sqrt(x.shape[1])


def initial_step(fun, t0, y, k1, rtol, atol, span, p):
    """Hairer, Nørsett & Wanner, Solving ODEs I, §II.4: a first step size per sample.

    p: the error estimate's order + 1 (5 for a 5(4) pair), as in Hairer's DOPRI5 (`IORD`).
    """
    with torch.no_grad():
        scale = atol + rtol * y.abs()
        d0, d1 = rms(y / scale), rms(k1 / scale)
        h0 = torch.where((d0 < 1e-5) | (d1 < 1e-5), 1e-6, 0.01 * d0 / d1.clamp_min(1e-300))
        h0 = torch.minimum(h0, span)
        y1 = y + h0.to(y.dtype)[:, None] * k1
        d2 = rms((fun(t0 + h0, y1) - k1) / scale) / h0
        dmax = torch.maximum(d1, d2)
        h1 = torch.where(
            dmax <= 1e-15,
            torch.clamp_min(h0 * 1e-3, 1e-6),
            (0.01 / dmax.clamp_min(1e-300)) ** (1.0 / p),
        )
        h = torch.minimum(torch.minimum(100 * h0, h1), span)
        return torch.where(torch.isfinite(h) & (h > 0), h, span * 1e-6)


def solve_adaptive(fun: RHS, tab: StageTableau, p: int, ctrl: StepController,
                   y: torch.Tensor, ts: torch.Tensor, stops: torch.Tensor, rtol: float,
                   atol: float, dt0, max_steps: int, compile: bool = False,
                   report: Callable[[torch.Tensor], None] | None = None):
    """Integrate with adaptive steps.

    Args:
        fun: the right-hand side on flat states, `fun(t [B], y [B, F]) -> [B, F]`.
        p: the error estimate's order + 1 (for the first step size; `ctrl` has its own).
        y: `[B, F]` initial states at `ts[0]`; ts: `[T]` float64 output times;
        stops: sorted float64 times in (t0, t_end] that steps land on, t_end last.
        dt0: the first step size, scalar or `[B]`, or None for `initial_step`'s.
        compile: run `attempt_step` compiled (`STEP`).
        report: called with each sample's time `[B]` after every step.
        The rest are `solve`'s.

    Returns:
        `(ys [B, T, F], status [B], stats)`, as `solve` returns them.
    """
    batch, feat = y.shape
    dev, f64 = y.device, torch.float64
    n_out = ts.numel()
    t0 = ts[0]

    t = t0.expand(batch).clone()  # (B,) float64
    k1 = fun(t, y)
    n_f = torch.ones(batch, dtype=torch.long, device=dev)
    span = (ts[-1] - t0).expand(batch)
    if dt0 is None:
        dt = initial_step(fun, t, y, k1, rtol, atol, span, p)
        n_f += 1
    else:
        dt = torch.as_tensor(dt0, dtype=f64, device=dev).expand(batch).clone()

    # Outputs: (column index [B, W], value [B, W, F]) per writing step, scattered into the
    # result once at the end (one gather in the backward pass instead of one full-size copy
    # per step); a spare column at index n_out takes the writes of masked-out lanes.
    out_cols = [torch.zeros(batch, 1, dtype=torch.long, device=dev)]
    out_vals = [y.unsqueeze(1)]
    stop_idx = torch.zeros(batch, dtype=torch.long, device=dev)
    stops_pad = torch.cat([stops, stops[-1:]])  # finished samples index one past the end
    status = torch.zeros_like(stop_idx)
    start_ok = torch.isfinite(k1).all(dim=1) & torch.isfinite(y).all(dim=1)
    status[~start_ok] = Status.NON_FINITE
    arange_out = torch.arange(n_out, device=dev)

    stages = Stages(tab.stages, batch, feat, y,
                    reuse=not (torch.is_grad_enabled() and k1.requires_grad))
    consts = Constants(tab, ctrl, stages, ts, stops_pad, stops.numel(), rtol, atol, max_steps)
    state = State(
        t=t, dt=dt, y=y, k1=k1, running=start_ok.clone(), stop_idx=stop_idx,
        stop_t=stops_pad[stop_idx],
        err_prev=torch.full((batch,), ctrl.initial_history(), dtype=f64, device=dev),
        n_steps=torch.zeros_like(stop_idx), n_accepted=torch.zeros_like(stop_idx),
        n_nonfinite=torch.zeros_like(stop_idx),
        out_idx=torch.ones(batch, dtype=torch.long, device=dev))
    while True:
        state, flags, step = STEP(compile, fun, consts, state)
        any_running, width, any_jumped, any_failed = flags.tolist()  # the step's one sync
        if any_failed:  # rare: record why those samples stopped
            why = torch.where(step.too_many, Status.NON_FINITE,
                              torch.where(step.underflow, Status.DT_UNDERFLOW,
                                          Status.MAX_STEPS))
            status = torch.where(step.failed, why, status)
        if width > 0:
            cols, vals = interpolate_outputs(ts, tab, step, state.out_idx, width, arange_out)
            out_cols.append(cols)
            out_vals.append(vals)
            state = state._replace(out_idx=state.out_idx + step.n_cross)
        if any_jumped:  # right-limit derivative at the stop, for those that landed there
            k1 = torch.where(step.jumped[:, None], fun(state.t, state.y), state.k1)
            n_f = n_f + state.running
            state = state._replace(k1=k1)
        if not any_running:
            break
        if report is not None:
            report(state.t)
    n_f += (tab.stages - 1) * state.n_steps
    stats = {"n_steps": state.n_steps, "n_accepted": state.n_accepted,
             "n_rejected": state.n_steps - state.n_accepted, "n_f_evals": n_f}
    return gather_outputs(out_cols, out_vals, n_out), status, stats


def attempt_step(fun: RHS, consts: Constants, state: State):
    """Attempt one step for every running sample; pure tensor code, no host sync.

    Returns:
        `(state, flags, attempt)`: the next `State`; `flags`, a `[4]` int64 tensor (anyone
        still running, the most outputs one sample crossed, anyone landed on an interior
        stop, anyone failed), read by the loop in its one sync; and the `Attempt`.
    """
    tab, ctrl, stages, ts, stops_pad, n_stops, rtol, atol, max_steps = consts
    (t, dt, y, k1, running, stop_idx, stop_t, err_prev, n_steps, n_acc, n_nonfinite,
     out_idx) = state

    # ---- attempt one step of size h (clipped so as not to cross the next stop)
    with torch.no_grad():
        to_stop = stop_t - t
        land = dt >= to_stop
        h = torch.where(running, torch.minimum(dt, to_stop), 0.0)
        t_new = torch.where(land, stop_t, t + h)
    y_new, err, f_new, hk = rk_step(fun, tab, stages, t, h, y, k1, t_new)

    # ---- error control and bookkeeping, outside autograd
    with torch.no_grad():
        scale = torch.maximum(y.abs(), y_new.abs()).mul_(rtol).add_(atol)
        r = rms(err / scale)
        finite = torch.isfinite(r)
        r = ctrl.ratio(r, finite)
        accept = running & (r <= 1.0)
        dt_next, err_prev = ctrl.propose(h, r, err_prev, accept)
        landed = accept & land
        # A step clipped at a stop says little about the step size the solution allows:
        # keep the proposal it was clipped from.
        dt_next = torch.where(landed, torch.maximum(dt_next, dt), dt_next)
        dt = torch.where(running, dt_next, dt)

        n_cross = torch.where(accept, torch.searchsorted(ts, t_new, right=True) - out_idx, 0)
        n_steps = n_steps + running
        n_acc = n_acc + accept
        stop_idx = stop_idx + landed
        stop_t = stops_pad[stop_idx]
        n_nonfinite = torch.where(finite, 0, n_nonfinite + running)
        not_done = stop_idx < n_stops
        too_many = n_nonfinite >= _MAX_NON_FINITE_REJECTS
        # The next step would not move the clock. Checked after accepted steps too: near a
        # blow-up the step shrinks geometrically while every step is accepted, and checking
        # only rejections let such a sample take thousands of steps that advance no time.
        t_next = torch.where(accept, t_new, t)
        underflow = t_next + dt <= t_next
        out_of_steps = n_steps >= max_steps
        failed = (too_many | underflow | out_of_steps) & running & not_done
        running_next = running & not_done & ~failed
        # Landing on an interior stop invalidates FSAL: f may change there (a new control).
        jumped = landed & not_done
        flags = torch.stack([running_next.any(), n_cross.max(), jumped.any(), failed.any()])

    # ---- advance accepted samples; FSAL: the last stage is f at the new state
    acc2 = accept[:, None]
    y_next = torch.where(acc2, y_new, y)
    k1 = torch.where(acc2, f_new, k1)
    state = State(t_next, dt, y_next, k1, running_next, stop_idx, stop_t, err_prev, n_steps,
                  n_acc, n_nonfinite, out_idx)
    return state, flags, Attempt(jumped, n_cross, failed, too_many, underflow, t, h, y, hk)


STEP = CompileCache(attempt_step)  # the step, compiled once per process when asked


def interpolate_outputs(ts: torch.Tensor, tab: StageTableau, step: Attempt,
                        out_idx: torch.Tensor, width: int, arange_out: torch.Tensor):
    """Evaluate the interpolant at the ≤ `width` output times each sample's step crossed.

    Returns `(cols [B, W], values [B, W, F])`: `values[b, w]` belongs in output column
    `out_idx[b] + w` for `w < n_cross[b]`; other lanes point at the spare column `n_out`.
    """
    t, h, y, hk = step.t, step.h, step.y, step.hk
    n_out = ts.numel()
    w = arange_out[:width]
    j = out_idx[:, None] + w  # (B, W)
    valid = w < step.n_cross[:, None]
    j = torch.where(valid, j, n_out)
    with torch.no_grad():
        h_safe = torch.where(h > 0, h, 1.0)
        theta = ((ts[j.clamp_max(n_out - 1)] - t[:, None]) / h_safe[:, None]).clamp(0.0, 1.0)
        powers = torch.stack([theta**k for k in range(1, len(tab.interp) + 1)], -1)  # (B, W, K)
        coef = (powers @ tab.interp).to(y.dtype)  # (B, W, s): b_i(θ)
    return j, y.unsqueeze(1) + torch.einsum("bwi,ibf->bwf", coef, hk)  # (B, W, F)


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
