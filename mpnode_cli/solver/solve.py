"""A batched explicit Runge–Kutta solver with per-sample adaptive steps, written for torch.

One entry point, `solve(f, y0, t_eval, method=..., ...) -> Solution`; the methods (Tsit5 by
default, Dopri5, RK4) are tableaus in `tableau.py`. Each sample of the batch has its
own time, step size, error control, controller history, counters and status, so a sample's
result does not depend on what else is in the batch (torchdiffeq shares one step size across
the batch; see docs/solver.md), and a sample that fails is frozen and marked while the others
go on.

This module checks the arguments, flattens each sample's state to `[F]`, gathers the
solve's settings into one `Problem` (`problem.py`), and hands over to one of two loops over
the same Runge–Kutta step (`runge_kutta.py`, recorded op by op by autograd, or `fused.py`,
with a backward written for the tableau): `adaptive.py` (error control in
`adaptive_step.py`, dense output in `dense.py`, an optional compiled step) or `fixed.py`
(`fixed_dt`). The result types are in `solution.py`, the step-size controllers, which own
the tolerances, in `controller.py`.
Given `restrict`, the adaptive solve compacts (`_adaptive`): once most samples are done it
restarts on the running ones, each from its own state, and merges their later outputs back.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence

import torch

from mpnode_cli.solver.adaptive import solve_adaptive
from mpnode_cli.solver.compile_cache import CompileCache
from mpnode_cli.solver.controller import ATOL, CONTROLLER, RTOL, StepController, controller_for
from mpnode_cli.solver.fixed import solve_fixed
from mpnode_cli.solver.options import MAX_STEPS, METHOD
from mpnode_cli.solver.problem import Problem
from mpnode_cli.solver.runge_kutta import RHS, stage_tableau
from mpnode_cli.solver.solution import STAT_NAMES, Solution, Status
from mpnode_cli.solver.tableau import get_method

__all__ = ["PROGRESS_SECONDS", "RHS", "Solution", "Status", "solve"]


def solve(
    f: RHS,
    y0: torch.Tensor,
    t_eval: torch.Tensor | Sequence[float],
    *,
    method: str = METHOD,
    rtol: float | None = None,
    atol: float | None = None,
    dt0: float | torch.Tensor | None = None,
    max_steps: int = MAX_STEPS,
    fixed_dt: float | None = None,
    tstops: torch.Tensor | Sequence[float] | None = None,
    compile: bool | CompileCache = False,
    controller: str | StepController = CONTROLLER,
    progress: Callable[[float], None] | None = None,
    fused: bool = True,
    compact: bool = True,
    restrict: Callable[[torch.Tensor], RHS] | None = None,
    restrict_block: int = 1,
    checkpoints: int | None = None,
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
        rtol, atol: the tolerances of the controller `controller` names (None: 1e-6 and
            1e-8, `controller.RTOL`, `ATOL`); never beside a controller object.
        dt0: first step size (scalar or `[B]`); by default chosen per sample by Hairer's
            heuristic (two extra evaluations of `f`).
        max_steps: attempted steps per sample before it is marked `MAX_STEPS`.
        fixed_dt: if given, take fixed steps (no error control) of at most this size, aligned
            so that every output time and every tstop is hit exactly.
        tstops: times that no step may cross (e.g. where a zero-order-hold control changes).
        compile: run the adaptive step through `torch.compile` (inductor): ~10 s to compile
            for a new `f`, shape or dtype, then about 2× faster on CPU
            (bench/results/solver.md); for long or repeated solves; ignored with `fixed_dt`.
            True compiles for this solve alone; a `CompileCache` shares its compiled graphs,
            and its fallback to the eager step after a failed compile, with every solve
            given the same one (`SolverOptions.solve_kwargs` gives the options' own).
        controller: adaptive step-size control, "pi" (proportional-integral, the default)
            or "i" (integral; fewer steps at loose tolerances on smooth solutions), or a
            controller object with its own tolerances and coefficients, e.g.
            `PIController(rtol=1e-8, atol=1e-10)`: a step is accepted when the RMS over
            the sample's elements of `err / (atol + rtol·max(|y|, |y_new|))` is ≤ 1.
        progress: if given, called now and then (at most every `PROGRESS_SECONDS`) with
            the fraction of the time span covered so far, the mean over samples, so that a
            long solve can show that it moves. Each call costs one host sync.
        fused: take uncompiled steps as one autograd node per stage, whose backward is the
            tableau's transposed sums (`fused.py`), about four times fewer ops a step than
            recording each op. False records every op of the step instead, as `compile`
            does (the same forward; the reference the tests hold the fused backward to).
        compact: with `restrict`, once at most half of the samples still run (and at least
            `adaptive.COMPACT_MIN_DROP` are done), go on with the running ones only, again
            as long as it pays. Each sample takes exactly the steps it would take alone: the
            result is the same up to the rounding of f over fewer rows. Adaptive uncompiled
            steps only (ignored with `compile` or `fixed_dt`).
        restrict: `restrict(index) -> f'`, the right-hand side of the samples `index`
            (`[B']` int64, sorted, into this batch) alone: `f'(t [B'], y [B', *S])`. None
            (the default): no compaction.
        restrict_block: samples are kept or dropped in whole blocks of this many
            consecutive samples, and `restrict` is only given such blocks (an ensemble's
            members, `mpnode_cli.models.ensemble`); 1: sample by sample. A batch that is
            not a multiple of it is not compacted.
        checkpoints: None (the default): backpropagate through every step, keeping its
            graph and what autograd saves of it (f's activations), so memory grows with
            the steps. An int C ≥ 1: each step is one autograd node that keeps nothing,
            and at most C solver states are kept (every s-th step's, s doubling as the
            solve grows); the backward pass reruns each step from the nearest state
            (keeping up to C more on the way) and backpropagates through it alone. The
            forward is the plain solve's bit for bit and the gradient plain backprop's
            to rounding, for 2–2.5 more forward passes with C = 64 up to 5000 steps
            (`checkpoint.py`, docs/solver.md, bench/results/memory.md). Needs the fused steps
            (`fused=True`); `compile` is ignored with it; no effect where autograd does
            not record the solve.

    Returns:
        A `Solution`. Gradients flow from `ys` to `y0` and to any parameters used by `f`
        (backpropagation through the solver's operations), not through the step-size
        choice. The fused step's backward is first-order only: `create_graph=True` raises
        (`fused=False` takes higher derivatives).
    """
    ts = _checked_times(y0, t_eval, fixed_dt)
    if checkpoints is not None and (isinstance(checkpoints, bool)
                                    or not isinstance(checkpoints, int) or checkpoints < 1):
        raise ValueError(f"checkpoints must be a positive integer or None, got {checkpoints!r}")
    if checkpoints is not None and not fused:
        raise ValueError("checkpoints reruns the fused steps: leave fused=True (fused=False "
                         "records every op, for higher derivatives, which checkpoints lack)")
    compiler = None if not compile or checkpoints is not None else (
        compile if isinstance(compile, CompileCache) else CompileCache())
    tableau = get_method(method, fixed_dt)
    ctrl = _controller(controller, rtol, atol)

    batch, shape, n_out = y0.shape[0], y0.shape[1:], ts.numel()
    y = y0.reshape(batch, -1).contiguous()  # (B, F); steps view it flat, e.g. y0 = x[:, 0]
    fun, shaped = _flat_and_shaped(f, batch, shape, y0.dtype)
    if n_out == 1:
        zeros = torch.zeros(batch, dtype=torch.long, device=y0.device)
        return Solution(ts, y0.unsqueeze(1), zeros, {k: zeros for k in STAT_NAMES})

    adaptive = fixed_dt is None
    problem = Problem(
        tab=stage_tableau(tableau, y.dtype, y0.device), ts=ts, stops=_stop_times(ts, tstops),
        shape=tuple(shape), dtype=y0.dtype, max_steps=max_steps, fused=fused,
        report=_Reporter(progress, ts), controller=ctrl,
        order=tableau.controller_order if adaptive else 0, dt0=dt0, compiler=compiler,
        restrict=restrict, fixed_dt=fixed_dt, checkpoints=checkpoints,
        block=_compaction_block(adaptive and compact and compiler is None, restrict,
                                restrict_block, batch))
    if adaptive:
        ys, status, stats = _adaptive(problem, fun, shaped, y)
    else:
        ys, status, stats = solve_fixed(problem, fun, shaped, y)
    return Solution(ts, ys.view(batch, n_out, *shape), status, stats)


def _controller(controller: str | StepController, rtol: float | None,
                atol: float | None) -> StepController:
    """The step-size controller `solve` was given, or the one it names, with `rtol` and
    `atol` (ValueError, one line, for an unknown name or tolerances beside an object)."""
    if isinstance(controller, StepController):
        if rtol is not None or atol is not None:
            raise ValueError("the controller object carries rtol and atol: give them to it "
                             f"({type(controller).__name__}(rtol=..., atol=...)), not to solve")
        return controller
    return controller_for(controller, RTOL if rtol is None else rtol,
                          ATOL if atol is None else atol)


def _checked_times(y0: torch.Tensor, t_eval, fixed_dt: float | None) -> torch.Tensor:
    """`t_eval` as a float64 `[T]` tensor on y0's device, after checking `solve`'s
    arguments (ValueError, one line, for a bad one)."""
    if y0.ndim < 1:
        raise ValueError("y0 must have a leading batch dimension: [B, *S]")
    if not (y0.is_floating_point() and y0.dtype in (torch.float32, torch.float64)):
        raise ValueError(f"y0 must be float32 or float64, got {y0.dtype}")
    ts = torch.as_tensor(t_eval, dtype=torch.float64, device=y0.device).reshape(-1)
    if ts.numel() < 1:
        raise ValueError("t_eval must hold at least one time")
    if ts.numel() > 1 and not bool((ts[1:] > ts[:-1]).all()):
        raise ValueError("t_eval must be strictly increasing")
    if fixed_dt is not None and not fixed_dt > 0:
        raise ValueError("fixed_dt must be positive")
    return ts


def _compaction_block(compact: bool, restrict, restrict_block: int, batch: int) -> int:
    """The block `_Adaptive` compacts by, or 0 for no compaction: without `restrict`, when
    turned off (or compiled), or when the batch is not whole blocks."""
    if not compact or restrict is None or restrict_block < 1 or batch % restrict_block:
        return 0
    return restrict_block


def _adaptive(problem: Problem, fun: RHS, shaped: RHS, y: torch.Tensor, start=None,
              index: torch.Tensor | None = None):
    """The adaptive solve with compaction: `(ys [B, T, F], status [B], stats)` of the
    samples `index` (None: the batch) from `start` (None: from `ts[0]`).

    `solve_adaptive` until it stops early, then the same on the samples that still run
    (`problem.restrict`), from where each one was, their later outputs, statuses and stats
    merged back into the batch's.
    """
    ys, status, stats, rest = solve_adaptive(problem, fun, shaped, y, start)
    if rest is None:
        return ys, status, stats
    running, block = rest.state.running, problem.block
    if block > 1:  # whole blocks with any sample still running
        running = running.view(-1, block).any(1).repeat_interleave(block)
    keep = running.nonzero().squeeze(1)  # (B',) sorted
    sub = rest.select(keep)
    full = keep if index is None else index.index_select(0, keep)
    sub_fun, sub_shaped = _flat_and_shaped(problem.restrict(full), keep.numel(),
                                           problem.shape, problem.dtype)
    ys_k, status_k, stats_k = _adaptive(problem, sub_fun, sub_shaped, sub.state.y, sub, full)
    # The kept samples' outputs from where each stopped on come from the restart.
    cols = torch.arange(problem.ts.numel(), device=y.device)
    later = (cols >= sub.state.out_idx[:, None])[..., None]  # (B', T, 1)
    ys = ys.index_copy(0, keep, torch.where(later, ys_k, ys.index_select(0, keep)))
    status = status.index_copy(0, keep, status_k)
    stats = {k: v.index_copy(0, keep, stats_k[k]) for k, v in stats.items()}
    return ys, status, stats


def _flat_and_shaped(f: RHS, batch: int, shape: tuple[int, ...], dtype: torch.dtype):
    """f on flat `[B, F]` states (the recorded steps') and on `[B, *S]` ones (the fused
    steps' nodes make and take them as they are), each returning the solve's dtype."""
    flat = len(shape) == 1  # f sees (B, F) already: skip two reshapes per evaluation

    def fun(t: torch.Tensor, yf: torch.Tensor) -> torch.Tensor:
        out = f(t, yf if flat else yf.view(batch, *shape))
        out = out if flat else out.reshape(batch, -1)
        return out if out.dtype == dtype else out.to(dtype)

    def shaped(t: torch.Tensor, ys: torch.Tensor) -> torch.Tensor:
        out = f(t, ys)
        return out if out.dtype == dtype else out.to(dtype)

    return fun, shaped


PROGRESS_SECONDS = 0.2  # shortest interval between two progress reports


class _Reporter:
    """Calls `progress(fraction)` at most every `PROGRESS_SECONDS` (a no-op without one)."""

    def __init__(self, progress: Callable[[float], None] | None, ts: torch.Tensor):
        self.progress = progress
        if progress is not None:  # three tensor ops that a solve without one skips
            self.t0, self.span = ts[0], ts[-1] - ts[0]
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
