"""One adaptive step of the whole batch in tensor code, with no host sync: its plan, the
Runge–Kutta stages (`runge_kutta.rk_step`), the error test and the next step size per
sample, and the counters and flags the loop reads (`adaptive.py`).

The step-size controller (`controller.py`) works on detached tensors: gradients flow
through the stages and the interpolant, not through the step-size choice (a prototype that
let r^(−1/5) into autograd produced NaN gradients near r = 0). It owns the error test's
tolerances; `Constants` holds it with what else every step reads. `attempt_step` records
every op on autograd's tape, and is what `torch.compile` takes whole (a solve's
`Problem.compiler`); the fused steps (`adaptive.FusedSteps`) share `plan_step` and
`control` with it.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import torch

from mpnode_cli.solver.controller import StepController
from mpnode_cli.solver.fused import StepTape
from mpnode_cli.solver.runge_kutta import RHS, Stages, StageTableau, rk_step

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
    tensor code, no host sync (what `Problem.compiler` compiles).

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
