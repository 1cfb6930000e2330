"""One explicit Runge–Kutta step for every sample of a batch, each with its own step size.

- Stage sums are one fused `addmv` per stage over a stage-major `[s, B, F]` buffer of h·k_i
  (the per-sample step size is applied once, when a stage is stored), so a stage costs two
  tensor ops plus `f`.
- Every step ends with f at its new state: the last stage of an FSAL method (Tsit5, Dopri5),
  or one stage appended to a method that is not (RK4), which the next step reuses as k₁.

The step has no host sync and no data-dependent shapes, so the adaptive loop can compile it
(docs/solver.md).
"""

from __future__ import annotations

import functools
import math
from collections.abc import Callable

import torch

from mpnode_cli.solver.tableau import ButcherTableau

RHS = Callable[[torch.Tensor, torch.Tensor], torch.Tensor]


class StageTableau:
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
        # The same rows over [y, h·k_1, ..., h·k_s]: stage input i is (1, a_i1, ..., a_ii−1)
        # times the first i + 1 of them (the fused step's backward, `fused.py`).
        a_ext = torch.cat([torch.ones(n, 1, dtype=torch.float64), a], 1).to(dtype=dtype,
                                                                           device=device)
        self.a_ext_rows = [a_ext[i, : i + 1].contiguous() for i in range(n)]
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
        self.interp_t = self.interp.T.contiguous()  # (s, K)


@functools.lru_cache(maxsize=64)
def stage_tableau(tableau: ButcherTableau, dtype: torch.dtype,
                  device: torch.device) -> StageTableau:
    """The `StageTableau` of a method, dtype and device, made once per process: building
    its ~20 small tensors cost more than a training step's error control."""
    return StageTableau(tableau, dtype, device)


class Stages:
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


def rk_step(fun: RHS, tab: StageTableau, stages: Stages, t: torch.Tensor, h: torch.Tensor,
            y: torch.Tensor, k1: torch.Tensor, t_end: torch.Tensor):
    """One Runge–Kutta step of size `h` for every sample.

    Args:
        fun: the right-hand side on flat states, `fun(t [B], y [B, F]) -> [B, F]`.
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
