"""A batched explicit Runge–Kutta solver with per-sample adaptive steps, written for torch.

One entry point, `solve(f, y0, t_eval, method=..., ...) -> Solution`; the methods (Tsit5 by
default, Dopri5, RK4) are tableaus in `tableau.py`. Each sample of the batch has its
own time, step size, error control, controller history, counters and status, so a sample's
result does not depend on what else is in the batch (torchdiffeq shares one step size across
the batch; see docs/solver.md), and a sample that fails is frozen and marked while the others
go on.

Design points (docs/solver.md):
- Stage sums are one fused `addmv` per stage over a stage-major `[s, B, F]` buffer of h·k_i
  (the per-sample step size is applied once, when a stage is stored), so a stage costs two
  tensor ops plus `f`.
- Every step ends with f at its new state: the last stage of an FSAL method (Tsit5, Dopri5),
  or one stage appended to a method that is not (RK4), which the next step reuses as k₁.
- Dense output uses the method's free interpolant, so steps are never shortened to hit
  output times; the outputs crossed by a step are written with a bounded, static-shape
  scatter (no `nonzero`).
- One host sync per step: the "anyone still running?" flag and the number of outputs to
  write travel together in one `.tolist()`.
- The step-size controller (`controller.py`) works on detached tensors:
  gradients flow through the stages and the interpolant, not through the step-size choice
  (a prototype that let r^(−1/5) into autograd produced NaN gradients near r = 0).
"""

from __future__ import annotations

import itertools
import math
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from enum import IntEnum

import torch

from mpnode_cli.solver.controller import controller_for
from mpnode_cli.solver.tableau import ButcherTableau, get_method

RHS = Callable[[torch.Tensor, torch.Tensor], torch.Tensor]

# After this many consecutive rejections for a non-finite error estimate (the step shrinks by
# 5× each time, so by ~1e14 in all) the right-hand side itself is taken to be non-finite.
_MAX_NON_FINITE_REJECTS = 20


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


def solve(
    f: RHS,
    y0: torch.Tensor,
    t_eval: torch.Tensor | Sequence[float],
    *,
    method: str = "tsit5",
    rtol: float = 1e-6,
    atol: float = 1e-8,
    dt0: float | torch.Tensor | None = None,
    max_steps: int = 100_000,
    fixed_dt: float | None = None,
    tstops: torch.Tensor | Sequence[float] | None = None,
    compile: bool = False,
    controller: str = "pi",
    progress: Callable[[float], None] | None = None,
) -> Solution:
    """Integrate `dy/dt = f(t, y)` for a batch of initial states with a Runge–Kutta method.

    Args:
        f: right-hand side `f(t, y) -> dy/dt`, called with `t: [B]` float64 (each sample's
            own time) and `y: [B, *S]`; returns `[B, *S]`. It should be free of Python side
            effects that depend on the call count (the number of calls is not fixed).
        y0: `[B, *S]` initial states at `t_eval[0]`; float32 or float64, any device. The
            solve runs in this dtype and on this device; time is kept in float64.
        t_eval: `[T]` strictly increasing output times, shared by the batch; `t_eval[0]` is
            the start time.
        method: a name of `tableau.METHODS`: "tsit5" (default) or "dopri5", 5(4) pairs
            with adaptive steps, or "rk4", the classic 4th-order method, which has no error
            estimate and so needs `fixed_dt`.
        rtol, atol: per-element tolerances; a step is accepted when the RMS over the
            sample's elements of `err / (atol + rtol·max(|y|, |y_new|))` is at most 1.
        dt0: first step size (scalar or `[B]`); by default chosen per sample by Hairer's
            heuristic (two extra evaluations of `f`).
        max_steps: attempted steps per sample before it is marked `MAX_STEPS`.
        fixed_dt: if given, take fixed steps (no error control) of at most this size, aligned
            so that every output time and every tstop is hit exactly.
        tstops: times that no step may cross (e.g. where a zero-order-hold control changes).
        compile: run the adaptive step through `torch.compile` (inductor). The first solve
            with a new `f`, shape or dtype compiles for ~10 s; later ones run about 2× faster
            on CPU (bench/results/solver.md). Worth it for long or repeated solves; ignored
            with `fixed_dt`.
        controller: adaptive step-size control, "pi" (proportional-integral, the default)
            or "i" (integral; fewer steps at loose tolerances on smooth solutions): a name
            of `controller.CONTROLLERS`.
        progress: if given, called now and then (at most every `PROGRESS_SECONDS`) with
            the fraction of the time span covered so far, the mean over samples, so that a
            long solve can show that it moves. Each call costs one host sync.

    Returns:
        A `Solution`. Gradients flow from `ys` to `y0` and to any parameters used by `f`
        (backpropagation through the solver's operations); the step-size controller is
        detached.
    """
    if y0.ndim < 1:
        raise ValueError("y0 must have a leading batch dimension: [B, *S]")
    if not (y0.is_floating_point() and y0.dtype in (torch.float32, torch.float64)):
        raise ValueError(f"y0 must be float32 or float64, got {y0.dtype}")
    device = y0.device
    ts = torch.as_tensor(t_eval, dtype=torch.float64, device=device).reshape(-1)
    if ts.numel() < 1:
        raise ValueError("t_eval must hold at least one time")
    if ts.numel() > 1 and not bool((ts[1:] > ts[:-1]).all()):
        raise ValueError("t_eval must be strictly increasing")
    if fixed_dt is not None and not fixed_dt > 0:
        raise ValueError("fixed_dt must be positive")
    tableau = get_method(method, fixed_dt)

    batch, shape = y0.shape[0], y0.shape[1:]
    n_out = ts.numel()
    y = y0.reshape(batch, -1).contiguous()  # (B, F); steps view it flat, e.g. y0 = x[:, 0]
    flat = len(shape) == 1  # f sees (B, F) already: skip two reshapes per evaluation

    def fun(t: torch.Tensor, yf: torch.Tensor) -> torch.Tensor:
        out = f(t, yf if flat else yf.view(batch, *shape))
        out = out if flat else out.reshape(batch, -1)
        return out if out.dtype == y0.dtype else out.to(y0.dtype)

    if n_out == 1:
        zeros = torch.zeros(batch, dtype=torch.long, device=device)
        return Solution(ts, y0.unsqueeze(1), zeros, {k: zeros for k in _STAT_NAMES})

    stops = _stop_times(ts, tstops)
    tab = _Tableau(tableau, y.dtype, device)
    report = _Reporter(progress, ts)
    if fixed_dt is not None:
        ys, status, stats = _solve_fixed(fun, tab, y, ts, stops, fixed_dt, max_steps, report)
    else:
        ys, status, stats = _solve_adaptive(fun, tab, tableau.controller_order, y, ts, stops,
                                            rtol, atol, dt0, max_steps, compile,
                                            controller, report)
    return Solution(ts, ys.view(batch, n_out, *shape), status, stats)


_STAT_NAMES = ("n_steps", "n_accepted", "n_rejected", "n_f_evals")
PROGRESS_SECONDS = 0.2  # shortest interval between two progress reports


class _Reporter:
    """Calls `progress(fraction)` at most every `PROGRESS_SECONDS` (a no-op without one)."""

    def __init__(self, progress: Callable[[float], None] | None, ts: torch.Tensor):
        self.progress, self.t0 = progress, ts[0]
        self.span = ts[-1] - ts[0]
        self.next = time.monotonic() + PROGRESS_SECONDS

    def __call__(self, t: torch.Tensor) -> None:
        """`t`: `[B]` each sample's time, or a scalar shared by all."""
        if self.progress is None or time.monotonic() < self.next:
            return
        self.progress(float(((t - self.t0) / self.span).clamp(0.0, 1.0).mean()))
        self.next = time.monotonic() + PROGRESS_SECONDS


def _stop_times(ts: torch.Tensor, tstops) -> torch.Tensor:
    """Sorted unique times in (t0, t_end] that steps land on exactly; t_end is the last."""
    t0, t1 = ts[0], ts[-1]
    if tstops is None:
        return t1.reshape(1)
    extra = torch.as_tensor(tstops, dtype=torch.float64, device=ts.device).reshape(-1)
    extra = extra[(extra > t0) & (extra < t1)]
    return torch.unique(torch.cat([extra, t1.reshape(1)]))  # sorted


class _Tableau:
    """A method's constants as tensors of the solve's dtype and device.

    The stages run are the method's, plus, for a method that is not FSAL, one stage with
    a = b and c = 1: f at the new state, which ends every step (it is the next step's k₁
    and the interpolant's end derivative). The last stage input is then always the new
    state, and a step costs `stages − 1` evaluations of f.
    """

    def __init__(self, tableau: ButcherTableau, dtype: torch.dtype, device: torch.device):
        c, rows, e = list(tableau.c), list(tableau.a), tableau.e
        if not tableau.fsal:
            c, rows = [*c, 1.0], [*rows, tableau.b]
            e = None if e is None else (*e, 0.0)
        n = len(c)
        a = torch.zeros(n, n, dtype=torch.float64)
        for i, row in enumerate(rows):
            a[i, : len(row)] = torch.tensor(row, dtype=torch.float64) if row else 0.0
        # Row i: the weights of stage i's input (the last row is b, the propagated solution).
        ae = a.to(dtype=dtype, device=device)  # (s, s)
        self.stages = n
        self.ae_rows = [ae[i, :i].contiguous() for i in range(n)]
        self.e = None if e is None else torch.tensor(e, dtype=dtype, device=device)  # (s,)
        # Stages with c = 1 are evaluated at the step's end from the left; they must come
        # last (true of every method here), after the inner nodes 0 < c < 1.
        n_end = len(c) - next(i for i in range(n) if all(x == 1.0 for x in c[i:]))
        if any(x == 1.0 for x in c[1 : n - n_end]):
            raise ValueError(f"method '{tableau.name}': stages with c = 1 must come last")
        self.n_end = n_end
        self.c_inner = torch.tensor(c[1 : n - n_end], dtype=torch.float64, device=device)
        self.neg_inf = torch.tensor(-math.inf, dtype=torch.float64, device=device)
        # Interpolant: b(θ) = [θ, θ², ..., θ^K] @ interp, interp (K, s).
        self.interp = torch.tensor(tableau.interp, dtype=torch.float64, device=device).T


class _Stages:
    """The stage buffer `[s, B, F]` of h·k_i and its views, made once per solve.

    Stage-major, so that a stage input y + Σ_j a_ij h·k_j is one addmv over the column-major
    (B·F, i) view and h is applied once, when a stage is stored. Reused from step to step
    unless autograd is recording (then each step needs a fresh buffer, since the graph keeps
    the previous one alive).
    """

    def __init__(self, stages: int, batch: int, feat: int, like: torch.Tensor, reuse: bool):
        self.shape, self.like, self.reuse = (stages, batch, feat), like, reuse
        self.views = self._views() if reuse else None

    def _views(self):
        s = self.shape[0]
        hk = torch.empty(self.shape, dtype=self.like.dtype, device=self.like.device)
        hk_t = hk.view(s, -1).T  # (B·F, s)
        return hk, [hk[i] for i in range(s)], [hk_t[:, :i] for i in range(s + 1)]

    def get(self):
        """`(buffer, per-stage views or None, column views)`.

        Views of a buffer that autograd writes into must be taken after the write (a view
        made before an in-place write counts as a leaf), so the recording case returns no
        stage views and the column views are taken lazily.
        """
        if self.reuse:
            return self.views
        hk = torch.empty(self.shape, dtype=self.like.dtype, device=self.like.device)
        return hk, None, _LazyColumns(hk)


class _LazyColumns:
    """`cols[i]` is the (B·F, i) column-major view of the first i stages, taken on access."""

    def __init__(self, hk: torch.Tensor):
        self.hk = hk

    def __getitem__(self, i: int) -> torch.Tensor:
        return self.hk.view(self.hk.shape[0], -1).T[:, :i]


def _rk_step(fun: RHS, tab: _Tableau, stages: _Stages, t: torch.Tensor, h: torch.Tensor,
             y: torch.Tensor, k1: torch.Tensor, t_end: torch.Tensor):
    """One Runge–Kutta step of size `h` for every sample.

    Args:
        t: `[B]` float64 step start; h: `[B]` float64 step sizes (0 freezes a sample);
        y: `[B, F]` state at t; k1: `[B, F]` f(t, y) (FSAL from the previous step);
        t_end: `[B]` float64 step end (t + h, or exactly the stop the step lands on). The
            c = 1 stages are evaluated just before it, so a zero-order-hold input that
            changes at a stop is seen from the left inside the step.

    Returns:
        y_new `[B, F]`; err `[B, F]`, the local error estimate h·Σ e_i k_i (None for a
        method without one); f_new `[B, F]`, f at (t_end, y_new); and the stage buffer
        `[s, B, F]` holding h·k_i.
    """
    batch, feat = y.shape
    hc = h.to(y.dtype)[:, None]  # (B, 1)
    t_left = torch.nextafter(t_end, tab.neg_inf)
    # Stage times; the last stages have c = 1, whose time is the step end (from the left).
    tcs = (*torch.addcmul(t[:, None], h[:, None], tab.c_inner).unbind(1),
           *(t_left,) * tab.n_end)
    hk, hk_i, hk_cols = stages.get()
    y_flat = y.view(-1)
    for i in range(tab.stages):
        if i == 0:
            fi = k1
        else:
            yi = torch.addmv(y_flat, hk_cols[i], tab.ae_rows[i]).view(batch, feat)
            fi = fun(tcs[i - 1], yi)
        if hk_i is None:
            hk[i] = fi * hc
        else:  # `out=` saves a temporary but is not differentiable
            torch.mul(fi, hc, out=hk_i[i])
    # The last row of the tableau is b, so the last stage input is the new state and the
    # last stage is the derivative at it.
    err = None if tab.e is None else torch.mv(hk_cols[tab.stages], tab.e).view(batch, feat)
    return yi, err, fi, hk


def _rms(x: torch.Tensor) -> torch.Tensor:
    """`[B, F]` → `[B]` root mean square over each sample's elements, in float64."""
    return torch.linalg.vector_norm(x, dim=1).double() / math.sqrt(x.shape[1])


def _initial_step(fun, t0, y, k1, rtol, atol, span, p):
    """Hairer, Nørsett & Wanner, Solving ODEs I, §II.4: a first step size per sample.

    p: the error estimate's order + 1 (5 for a 5(4) pair), as in Hairer's DOPRI5 (`IORD`).
    """
    with torch.no_grad():
        scale = atol + rtol * y.abs()
        d0, d1 = _rms(y / scale), _rms(k1 / scale)
        h0 = torch.where((d0 < 1e-5) | (d1 < 1e-5), 1e-6, 0.01 * d0 / d1.clamp_min(1e-300))
        h0 = torch.minimum(h0, span)
        y1 = y + h0.to(y.dtype)[:, None] * k1
        d2 = _rms((fun(t0 + h0, y1) - k1) / scale) / h0
        dmax = torch.maximum(d1, d2)
        h1 = torch.where(
            dmax <= 1e-15,
            torch.clamp_min(h0 * 1e-3, 1e-6),
            (0.01 / dmax.clamp_min(1e-300)) ** (1.0 / p),
        )
        h = torch.minimum(torch.minimum(100 * h0, h1), span)
        return torch.where(torch.isfinite(h) & (h > 0), h, span * 1e-6)


def _solve_adaptive(fun, tab, p, y, ts, stops, rtol, atol, dt0, max_steps, compile=False,
                    controller="pi", report=None):
    """The adaptive loop; p is the error estimate's order + 1 (the controller's exponent)."""
    batch, feat = y.shape
    dev, f64 = y.device, torch.float64
    ctrl = controller_for(controller, p)
    n_out, n_stops = ts.numel(), stops.numel()
    t0 = ts[0]

    t = t0.expand(batch).clone()  # (B,) float64
    k1 = fun(t, y)
    n_f = torch.ones(batch, dtype=torch.long, device=dev)
    span = (ts[-1] - t0).expand(batch)
    if dt0 is None:
        dt = _initial_step(fun, t, y, k1, rtol, atol, span, p)
        n_f += 1
    else:
        dt = torch.as_tensor(dt0, dtype=f64, device=dev).expand(batch).clone()

    # Outputs: (column index [B, W], value [B, W, F]) per writing step, scattered into the
    # result once at the end (one gather in the backward pass instead of one full-size copy
    # per step); a spare column at index n_out takes the writes of masked-out lanes.
    out_cols = [torch.zeros(batch, 1, dtype=torch.long, device=dev)]
    out_vals = [y.unsqueeze(1)]
    out_idx = torch.ones(batch, dtype=torch.long, device=dev)  # next output to fill
    stop_idx = torch.zeros(batch, dtype=torch.long, device=dev)
    stops_pad = torch.cat([stops, stops[-1:]])  # finished samples index one past the end
    err_prev = torch.full((batch,), ctrl.initial_history(), dtype=f64, device=dev)
    n_steps = torch.zeros(batch, dtype=torch.long, device=dev)
    n_acc = torch.zeros_like(n_steps)
    n_nonfinite = torch.zeros_like(n_steps)  # consecutive rejections for NaN/inf
    status = torch.zeros_like(n_steps)
    start_ok = torch.isfinite(k1).all(dim=1) & torch.isfinite(y).all(dim=1)
    status[~start_ok] = Status.NON_FINITE
    running = start_ok.clone()
    arange_out = torch.arange(n_out, device=dev)

    stop_t = stops_pad[stop_idx]  # (B,) next time a step must land on
    stages = _Stages(tab.stages, batch, feat, y,
                     reuse=not (torch.is_grad_enabled() and k1.requires_grad))
    consts = (tab, ctrl, stages, ts, stops_pad, n_stops, rtol, atol, max_steps)
    state = (t, dt, y, k1, running, stop_idx, stop_t, err_prev, n_steps, n_acc, n_nonfinite,
             out_idx)
    step = _compiled_step() if compile and not _COMPILE_FAILED else _step
    while True:
        try:
            state, flags, extra = step(fun, consts, state)
        except Exception as exc:
            if step is _step:
                raise
            _compile_failed(exc)  # any compiler failure: run eagerly (f's own errors recur)
            step = _step
            state, flags, extra = step(fun, consts, state)
        any_running, width, any_jumped, any_failed = flags.tolist()  # the step's one sync
        jumped, n_cross, failed, code, (t_old, h, y_old, hk) = extra
        if any_failed:  # rare: record why those samples stopped
            too_many, underflow = code
            why = torch.where(too_many, Status.NON_FINITE,
                              torch.where(underflow, Status.DT_UNDERFLOW, Status.MAX_STEPS))
            status = torch.where(failed, why, status)
        if width > 0:
            out_idx = state[-1]
            cols, vals = _interpolate_outputs(ts, tab, t_old, h, y_old, hk, out_idx, n_cross,
                                              width, arange_out)
            out_cols.append(cols)
            out_vals.append(vals)
            state = (*state[:-1], out_idx + n_cross)
        if any_jumped:  # right-limit derivative at the stop, for those that landed there
            t_new, y_new, k1_new = state[0], state[2], state[3]
            k1_new = torch.where(jumped[:, None], fun(t_new, y_new), k1_new)
            n_f = n_f + state[4]
            state = (*state[:3], k1_new, *state[4:])
        if not any_running:
            break
        if report is not None:
            report(state[0])
    (t, dt, y, k1, running, stop_idx, stop_t, err_prev, n_steps, n_acc, n_nonfinite,
     out_idx) = state
    n_f += (tab.stages - 1) * n_steps
    stats = {"n_steps": n_steps, "n_accepted": n_acc, "n_rejected": n_steps - n_acc,
             "n_f_evals": n_f}
    return _gather_outputs(out_cols, out_vals, n_out), status, stats


def _gather_outputs(cols: list[torch.Tensor], vals: list[torch.Tensor], n_out: int):
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


def _compiled_step():
    """The step compiled once per process (torch.compile caches a graph per f). Automatic
    dynamic shapes (`dynamic=None`): a second size of a dimension (a horizon curriculum's
    next horizon, a smaller last batch) recompiles once with that dimension symbolic, and
    every later size reuses it, instead of one compile per size up to the cache limit."""
    global _STEP_COMPILED
    if _STEP_COMPILED is None:
        import warnings

        # Compiling traces the step's backward under autograd's anomaly mode, which prints
        # the forward's stack as a UserWarning when anything stops that trace: a Ctrl-C or
        # SIGTERM during the first epochs (the interrupt itself is reported as usual), or a
        # compiler failure (which `_compile_failed` reports in one line).
        warnings.filterwarnings("ignore", message="Error detected in ",
                                category=UserWarning, module="torch.autograd.graph")
        # One process may train several models (an experiment's steps, run one after
        # another): each new node count, batch layout or grad mode adds a variant of the
        # step, and past dynamo's default of 8 every further one would run eagerly, with a
        # warning, for the rest of the process (seen: a gene 4×4 training, then its 8×8
        # finetune). Each variant compiles once, so a higher cap costs only those compiles.
        import torch._dynamo.config as dynamo_config

        dynamo_config.recompile_limit = max(dynamo_config.recompile_limit, 64)
        _STEP_COMPILED = torch.compile(_step, dynamic=None)
    return _STEP_COMPILED


_STEP_COMPILED = None
_COMPILE_FAILED = False


def _compile_failed(exc: Exception) -> None:
    """Compiling failed (no C++ compiler, an unsupported op, ...): warn once, then every
    later solve of this process runs the eager step, which computes the same thing."""
    global _COMPILE_FAILED
    if not _COMPILE_FAILED:
        import warnings

        first = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
        warnings.warn(f"torch.compile of the solver step failed ({first[:200]}); "
                      "running it uncompiled", RuntimeWarning, stacklevel=3)
    _COMPILE_FAILED = True


def _step(fun, consts, state):
    """Attempt one step for every running sample; pure tensor code, no host sync."""
    tab, ctrl, stages, ts, stops_pad, n_stops, rtol, atol, max_steps = consts
    (t, dt, y, k1, running, stop_idx, stop_t, err_prev, n_steps, n_acc, n_nonfinite,
     out_idx) = state

    # ---- attempt one step of size h (clipped so as not to cross the next stop)
    with torch.no_grad():
        to_stop = stop_t - t
        land = dt >= to_stop
        h = torch.where(running, torch.minimum(dt, to_stop), 0.0)
        t_new = torch.where(land, stop_t, t + h)
    y_new, err, f_new, hk = _rk_step(fun, tab, stages, t, h, y, k1, t_new)

    # ---- error control and bookkeeping, outside autograd
    with torch.no_grad():
        scale = torch.maximum(y.abs(), y_new.abs()).mul_(rtol).add_(atol)
        r = _rms(err / scale)
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
    state = (t_next, dt, y_next, k1, running_next, stop_idx, stop_t, err_prev, n_steps, n_acc,
             n_nonfinite, out_idx)
    code = (too_many, underflow)
    return state, flags, (jumped, n_cross, failed, code, (t, h, y, hk))


def _interpolate_outputs(ts, tab, t, h, y, hk, out_idx, n_cross, width, arange_out):
    """Evaluate the interpolant at the ≤ `width` output times each sample crossed.

    Returns `(cols [B, W], values [B, W, F])`: `values[b, w]` belongs in output column
    `out_idx[b] + w` for `w < n_cross[b]`; other lanes point at the spare column `n_out`.
    """
    n_out = ts.numel()
    w = arange_out[:width]
    j = out_idx[:, None] + w  # (B, W)
    valid = w < n_cross[:, None]
    j = torch.where(valid, j, n_out)
    with torch.no_grad():
        h_safe = torch.where(h > 0, h, 1.0)
        theta = ((ts[j.clamp_max(n_out - 1)] - t[:, None]) / h_safe[:, None]).clamp(0.0, 1.0)
        powers = torch.stack([theta**k for k in range(1, len(tab.interp) + 1)], -1)  # (B, W, K)
        coef = (powers @ tab.interp).to(y.dtype)  # (B, W, s): b_i(θ)
    return j, y.unsqueeze(1) + torch.einsum("bwi,ibf->bwf", coef, hk)  # (B, W, F)


def _fixed_grid(ts: torch.Tensor, stops: torch.Tensor, fixed_dt: float) -> list[float]:
    """Step end times: every output time and stop, with equal substeps of ≤ fixed_dt between."""
    marks = torch.unique(torch.cat([ts, stops])).tolist()
    grid = []
    for a, b in itertools.pairwise(marks):
        n = max(1, math.ceil((b - a) / fixed_dt - 1e-9))
        grid.extend(a + (b - a) * (i / n) for i in range(1, n))
        grid.append(b)
    return grid


def _solve_fixed(fun, tab, y, ts, stops, fixed_dt, max_steps, report=None):
    batch = y.shape[0]
    dev = y.device
    n_out = ts.numel()
    out_times = ts.tolist()
    grid = _fixed_grid(ts, stops, fixed_dt)
    interior_stops = set(stops[:-1].tolist())
    zero = torch.zeros((), dtype=torch.float64, device=dev)
    n_extra = 0

    t_prev = out_times[0]
    t = torch.full((batch,), t_prev, dtype=torch.float64, device=dev)
    k1 = fun(t, y)
    stages = _Stages(tab.stages, batch, y.shape[1], y,
                     reuse=not (torch.is_grad_enabled() and k1.requires_grad))
    running = torch.isfinite(k1).all(dim=1) & torch.isfinite(y).all(dim=1)
    status = torch.where(running, Status.SUCCESS, Status.NON_FINITE)
    n_steps = torch.zeros(batch, dtype=torch.long, device=dev)
    outs = [y] + [None] * (n_out - 1)
    nan_row = torch.full_like(y, math.nan)
    j = 1
    for step, t_next in enumerate(grid):
        if step >= max_steps:
            status = torch.where(running, Status.MAX_STEPS, status)
            running = torch.zeros_like(running)
            break
        h = torch.where(running, t_next - t_prev, zero)
        t_end = torch.full_like(t, t_next)
        y_new, _, f_new, _ = _rk_step(fun, tab, stages, t, h, y, k1, t_end)
        ok = running & torch.isfinite(y_new).all(dim=1) & torch.isfinite(f_new).all(dim=1)
        status = torch.where(running & ~ok, Status.NON_FINITE, status)
        n_steps += running
        y = torch.where(ok[:, None], y_new, y)
        k1 = torch.where(ok[:, None], f_new, k1)
        running = ok
        t = t_end
        t_prev = t_next
        if t_next in interior_stops:  # f may jump here: FSAL's left limit is not valid
            k1 = fun(t, y)
            n_extra += 1
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
