"""A Runge–Kutta step whose backward is written for the tableau instead of recorded op by op.

Everything a step does besides calling f is linear in the stages: the stage inputs
Y_i = y + Σ_j a_ij·h·k_j, the new state, the error estimate and the interpolant
y(θ) = y + Σ_j b_j(θ)·h·k_j, with coefficients that autograd never differentiates (h and θ
come from the detached controller). So the backward of the step's own work is the
transposed combination: with λ_j the adjoint of h·k_j and λ_y that of y,

    λ_y += g_i,   λ_j += a_ij·g_i   (j < i)        for each stage input's adjoint g_i,

and k_j's adjoint is h·λ_j once every later stage has added its part: the discrete adjoint
of an explicit Runge–Kutta step (W. W. Hager, "Runge–Kutta methods in optimal control and
the transformed adjoint system", Numer. Math. 87 (2000) 247–282), with f's own vector-
Jacobian products left to autograd. torchode and diffrax backpropagate through the same
sums op by op. Here each stage input is one
autograd node, `_Stage`, whose backward is one rank-1 update of a step-wide `[s + 1, B·F]`
adjoint buffer and one product; the step's end, `_End`, selects the next state and k₁ per
sample (accepted or not) and writes the dense outputs; `_Outputs` hands the result's
gradient to the `_End` nodes. f stays on autograd's tape between them, so gradients with
respect to its parameters are autograd's own.

The nodes of one step share a `TapeRecord` (and those of one solve a `StepTape`): a
node's backward adds to the buffer that an earlier-stage node's backward reads. That
order is autograd's own: the input of stage i + 1 depends on k_i = f(Y_i), so its node's
backward always runs before that of stage i. The backward is not itself differentiable:
with `create_graph` it raises (`fused=False` records every op, and is). Against recording
each op (the stage buffer's slice writes and their copies in the backward, the
interpolant's einsum, the outputs' final scatter) the solver's part of a training step
runs a third of the ops in the backward and 28% fewer in the forward (docs/solver.md,
"The fused step").
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from mpnode_cli.solver.dense import write_lanes
from mpnode_cli.solver.runge_kutta import RHS, StageTableau


class StepTape:
    """What the fused steps of one solve share.

    Attributes:
        tab: the method's constants.
        shape: `(B, *S)` the states' shape as f sees them; feat: F, the flat size.
        record: whether autograd records the steps (else the nodes' forwards run alone).
        hk: `[s, B, F]` the current step's h·k_i, reused every step (no backward reads it).
        cols: `cols[i]` the `(B·F, i)` column-major view of its first i stages.
        rows: `rows[i]` the `[B, *S]` view of stage i, which f's value is stored into.
        out: `[B·T + 1, F]` the dense outputs, NaN until written; the spare last row takes
            the writes of masked-out lanes (None for a solve without dense output).
        g_out: `[B·T + 1, F]` the outputs' gradient (last row 0), set by `_Outputs`' backward.
    """

    def __init__(self, tab: StageTableau, y: torch.Tensor, shape: tuple[int, ...],
                 record: bool, n_out: int | None = None):
        batch, feat = y.shape
        self.tab, self.shape, self.feat, self.record = tab, shape, feat, record
        self.hk = torch.empty(tab.stages, batch, feat, dtype=y.dtype, device=y.device)
        hk_t = self.hk.view(tab.stages, -1).T  # (B·F, s)
        self.cols = [hk_t[:, :i] for i in range(tab.stages + 1)]
        self.rows = [self.hk[i].view(shape) for i in range(tab.stages)]
        self.out = self.g_out = None
        if n_out is not None:
            self.out = torch.full((batch * n_out + 1, feat), math.nan, dtype=y.dtype,
                                  device=y.device)


@dataclass
class TapeRecord:
    """One step's share of the tape: its per-sample step size, its end's selection and
    dense-output lanes, and the adjoint buffer its backward builds.

    hc: `[B, 1]` h in the state's dtype, hc_s the same as `[B, 1, ..., 1]` (broadcasting
    against `[B, *S]`); y, k1: `[B, F]` the step's start and f there; y_flat: y as `[B·F]`;
    y_new: `[B, F]` the last stage input (the new state); accept: `[B, 1]` bool;
    rows: `[B·W]` output rows of the dense-output lanes; coef: `[B, W, s]` their weights
    b_i(θ) of h·k_i (y's is 1); lam: `[s + 1, B·F]` adjoints of
    `[y, h·k_1, ..., h·k_s]`; gk1: `[B, F]` the part of k₁'s adjoint that `_End` passes on
    for the samples that keep k₁ (a rejected step); last: `[B, *S]` the last stage's input
    as autograd recorded it.
    """

    tape: StepTape
    hc: torch.Tensor
    hc_s: torch.Tensor
    y: torch.Tensor | None
    k1: torch.Tensor | None
    y_flat: torch.Tensor | None
    y_new: torch.Tensor | None = None
    accept: torch.Tensor | None = None
    rows: torch.Tensor | None = None
    coef: torch.Tensor | None = None
    lam: torch.Tensor | None = None
    gk1: torch.Tensor | None = None
    last: torch.Tensor | None = None

    def adjoint(self) -> torch.Tensor:
        """The step's adjoint buffer (made by `_End`'s backward, the step's first)."""
        if self.lam is None:
            tape = self.tape
            self.lam = torch.zeros(tape.tab.stages + 1, self.hc.shape[0] * tape.feat,
                                   dtype=self.hc.dtype, device=self.hc.device)
        return self.lam


def _first_order_only() -> None:
    """Raise where a backward would be recorded for a second derivative (`create_graph`):
    the nodes' buffers are written in place, outside autograd. (`once_differentiable`'s
    error node is pruned by `autograd.grad(..., inputs=...)`, which would then return a
    second derivative without the solver's part, silently.)"""
    if torch.is_grad_enabled():
        raise RuntimeError("solve's fused step has a first-order backward only; for higher "
                           "derivatives (create_graph=True) pass fused=False")


def _store(rec: TapeRecord, i: int, k: torch.Tensor) -> None:
    """`hk[i] = h·k`, from f's `[B, *S]` values or k₁'s `[B, F]`."""
    row = rec.tape.rows[i]
    if k.shape == row.shape:
        torch.mul(k, rec.hc_s, out=row)
    else:
        torch.mul(k.reshape(rec.hc.shape[0], -1), rec.hc, out=rec.tape.hk[i])


def _stage_input(rec: TapeRecord, i: int, k_prev: torch.Tensor) -> torch.Tensor:
    """Store h·k_{i−1} and return stage i's input y + Σ_{j<i} a_ij·h·k_j, `[B, *S]`."""
    tape = rec.tape
    _store(rec, i - 1, k_prev)
    y_i = torch.addmv(rec.y_flat, tape.cols[i], tape.tab.ae_rows[i])  # (B·F,)
    if i == tape.tab.stages - 1:  # the last row of a is b: the new state, kept untracked
        rec.y_new = y_i.view(rec.y.shape)
    return y_i.view(tape.shape)


class _Stage(torch.autograd.Function):
    """Stage i's input from k_{i−1}; see the module docstring. It also takes `prev`, the
    previous stage's input (y for stage 1), whose adjoint it returns only for stage 1 (y's,
    complete then): the chain End → stage s−1 → ... → stage 1 → y keeps every node of the
    step in the backward, also where f's values carry no graph (an f without parameters
    that ignores the state), and a None gradient costs autograd nothing."""

    @staticmethod
    def forward(ctx, rec: TapeRecord, i: int, k_prev: torch.Tensor, prev: torch.Tensor):
        ctx.set_materialize_grads(False)
        ctx.rec, ctx.i, ctx.k_shape = rec, i, k_prev.shape
        return _stage_input(rec, i, k_prev)

    @staticmethod
    def backward(ctx, g):
        _first_order_only()
        rec, i = ctx.rec, ctx.i
        lam = rec.adjoint()
        if g is not None:  # λ[:i+1] += (1, a_i1, ..., a_ii−1) ⊗ g
            lam[: i + 1].addr_(rec.tape.tab.a_ext_rows[i], g.reshape(-1))
        lam_k = lam[i].view(rec.hc.shape[0], -1)
        if i > 1:
            return None, None, (lam_k * rec.hc).view(ctx.k_shape), None
        gk = lam_k * rec.hc if rec.gk1 is None else torch.addcmul(rec.gk1, lam_k, rec.hc)
        # The step's last node: its buffers can go (the graph keeps `rec` to its end).
        rec.lam = rec.gk1 = None
        return None, None, gk.view(ctx.k_shape), lam[0].view(lam_k.shape)


def fused_stages(fun: RHS, tab: StageTableau, tape: StepTape, t: torch.Tensor,
                 h: torch.Tensor, y: torch.Tensor, k1: torch.Tensor, t_end: torch.Tensor):
    """The stages of one step, as `runge_kutta.rk_step` computes them (the same ops).

    Args:
        fun: the right-hand side on `[B, *S]` states (`tape.shape`).
        t, h, y, k1, t_end: as `rk_step`'s (`y`, `k1`: `[B, F]`).

    Returns:
        `(rec, y_new [B, F], err [B, F] or None, f_new [B, *S])`; `end_step(rec, ...)`
        finishes the step.
    """
    hc = h.to(y.dtype)[:, None]  # (B, 1)
    with torch.no_grad():
        rec = TapeRecord(tape, hc, hc.view(tape.shape[:1] + (1,) * (len(tape.shape) - 1)), y,
                         k1, y.view(-1))
    t_left = torch.nextafter(t_end, tab.neg_inf)
    tcs = (*torch.addcmul(t[:, None], h[:, None], tab.c_inner).unbind(1),
           *(t_left,) * tab.n_end)
    fi, yi = k1, y
    for i in range(1, tab.stages):
        if tape.record:
            yi = _Stage.apply(rec, i, fi, yi)
        else:
            yi = _stage_input(rec, i, fi)
        fi = fun(tcs[i - 1], yi)
    rec.last = yi  # the new state as recorded, which `_End` takes
    # f at the new state (the last stage input), stored untracked (`_End` takes k_s's
    # adjoint) for the error estimate and the interpolant.
    with torch.no_grad():
        _store(rec, tab.stages - 1, fi)
        err = None if tab.e is None else torch.mv(tape.cols[tab.stages], tab.e).view(y.shape)
    return rec, rec.y_new, err, fi


def _end(rec: TapeRecord, k_last: torch.Tensor):
    """The next `(y, k₁)`, each `[B, F]`: the step's end where accepted, its start where not;
    and the dense outputs the step crossed, written into `tape.out`."""
    tape = rec.tape
    y_next = torch.where(rec.accept, rec.y_new, rec.y)
    k1_next = torch.where(rec.accept, k_last.reshape(rec.y.shape), rec.k1)
    if rec.rows is not None:
        write_lanes(tape.out, rec.rows, rec.coef, tape.hk, rec.y)
    rec.y = rec.k1 = rec.y_new = rec.y_flat = rec.last = None  # not needed past the step
    return y_next, k1_next


class _End(torch.autograd.Function):
    """The step's end from k_s = f(t + h, y_new); see `_end` and the module docstring. It
    takes the last stage's input (y_new as recorded) for the graph's sake only (see
    `_Stage`): y_new's adjoint goes into the step's buffer."""

    @staticmethod
    def forward(ctx, rec: TapeRecord, k_last: torch.Tensor, last: torch.Tensor):
        ctx.set_materialize_grads(False)
        ctx.rec, ctx.k_shape = rec, k_last.shape
        return _end(rec, k_last)

    @staticmethod
    def backward(ctx, gy, gk):
        _first_order_only()
        rec = ctx.rec
        tape, hc = rec.tape, rec.hc
        tab, s, batch = tape.tab, tape.tab.stages, hc.shape[0]
        rec.lam = rec.gk1 = None  # a new backward pass (retain_graph) starts from zero
        lam = rec.adjoint()
        if gy is not None:
            # y enters y_new with weight 1, so y's adjoint takes all of gy; y_new's stages
            # take it only where the step was accepted.
            lam[0].copy_(gy.reshape(-1))
            lam[1:s].addr_(tab.ae_rows[s - 1], torch.where(rec.accept, gy, 0.0).reshape(-1))
        if rec.rows is not None and tape.g_out is not None:
            g_lanes = tape.g_out.index_select(0, rec.rows).view(batch, -1, tape.feat)
            lam[0] += g_lanes.sum(1).view(-1)
            # (B, s, F) into the stage-major rows; an in-place baddbmm_ on that transposed
            # view would run one matmul per sample.
            lam_k = torch.bmm(rec.coef.transpose(1, 2), g_lanes).transpose(0, 1)
            lam[1:].view(s, batch, tape.feat).add_(lam_k)
        gk_last = lam[s].view(batch, -1) * hc
        if gk is not None:
            gk_last += torch.where(rec.accept, gk, 0.0)
            rec.gk1 = torch.where(rec.accept, 0.0, gk)
        return None, gk_last.view(ctx.k_shape), None


def end_step(rec: TapeRecord, f_new: torch.Tensor, accept: torch.Tensor,
             rows: torch.Tensor | None = None, coef: torch.Tensor | None = None):
    """Finish a step of `fused_stages`: the next `(y, k₁)`, each `[B, F]`.

    Args:
        f_new: `[B, *S]` f at the new state (`fused_stages`' last value).
        accept: `[B]` bool, the samples whose step was accepted.
        rows: `[B·W]` rows of `tape.out` that the dense-output lanes fill (the spare last
            row for masked-out lanes), with coef `[B, W, s]` (float64), their weights b_i(θ)
            of h·k_i; None when the step crossed no output.
    """
    rec.accept, rec.rows = accept[:, None], rows
    # Contiguous (B, W, s): the backward's bmm takes its per-sample transpose, which a
    # permuted layout would send down bmm's slow path (measured: ~0.2 ms a training step).
    rec.coef = None if coef is None else coef.to(rec.hc.dtype,
                                                 memory_format=torch.contiguous_format)
    if rec.tape.record:
        return _End.apply(rec, f_new, rec.last)
    return _end(rec, f_new)


class _Outputs(torch.autograd.Function):
    """`tape.out` as the solve's `[B, T, F]` result; its backward hands the gradient to the
    steps' `_End` nodes (which `y_last` and `k1_last`, the last step's, depend on)."""

    @staticmethod
    def forward(ctx, tape: StepTape, y0: torch.Tensor, y_last: torch.Tensor,
                k1_last: torch.Tensor):
        ctx.set_materialize_grads(False)
        ctx.tape = tape
        return tape.out[:-1].view(y0.shape[0], -1, tape.feat)

    @staticmethod
    def backward(ctx, g):
        _first_order_only()
        tape = ctx.tape
        if g is None:
            tape.g_out = None
            return None, None, None, None
        flat = g.reshape(-1, tape.feat)  # (B·T, F)
        tape.g_out = torch.cat([flat, flat.new_zeros(1, tape.feat)])
        return None, g[:, 0], None, None


def start_outputs(tape: StepTape, y0: torch.Tensor) -> None:
    """Write the first output column: the initial states `y0 [B, F]`."""
    with torch.no_grad():
        tape.out[:-1].view(y0.shape[0], -1, tape.feat)[:, 0] = y0


def collect_outputs(tape: StepTape, y0: torch.Tensor, y_last: torch.Tensor,
                    k1_last: torch.Tensor) -> torch.Tensor:
    """The `[B, T, F]` dense outputs of the solve, NaN where none was written."""
    if tape.record:
        return _Outputs.apply(tape, y0, y_last, k1_last)
    return tape.out[:-1].view(y0.shape[0], -1, tape.feat)
