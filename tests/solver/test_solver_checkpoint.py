"""Tests of checkpointed backpropagation through the solve (`solve(..., checkpoints=C)`,
`mpnode_cli/solver/checkpoint.py`): the gradients are plain backprop's, in float64, on an
MLP field and on a graph-coupled one, adaptive (with tstops, with compaction, a batch whose
samples take different numbers of steps) and fixed steps; the memory the solve holds stays
flat as the steps grow 10× while plain backprop's grows (torch's profiler, and the tensors
autograd saves); the reruns stay within revolve's bound; a right-hand side that is not
deterministic, or hides a tensor that needs a gradient, is refused."""

from __future__ import annotations

import itertools
import math

import pytest
import torch
from torch.profiler import ProfilerActivity, profile

from mpnode_cli.solver import checkpoint, solve

F64 = torch.float64


def _mlp(features: int, hidden: int, seed: int) -> torch.nn.Module:
    torch.manual_seed(seed)
    return torch.nn.Sequential(torch.nn.Linear(features, hidden), torch.nn.Tanh(),
                               torch.nn.Linear(hidden, features)).to(F64)


def _rotation(features: int, omega: float) -> torch.Tensor:
    """`[F, F]` skew blocks: an oscillation that makes the solve take many steps."""
    j = torch.zeros(features, features, dtype=F64)
    for i in range(0, features - 1, 2):
        j[i, i + 1], j[i + 1, i] = omega, -omega
    return j


class MLPField:
    """ẏ = ω_b·J y + s·MLP(y) on `[B, F]`: ω per sample (so samples take different
    numbers of steps), s = exp(log_s) a non-leaf tensor that f closes over."""

    def __init__(self, batch: int, features: int = 4, omega=(3.0,)):
        self.net = _mlp(features, 16, seed=0)
        self.log_s = torch.tensor(math.log(0.3), dtype=F64, requires_grad=True)
        self.omega = torch.tensor(omega, dtype=F64).repeat(batch)[:batch]
        self.j = _rotation(features, 1.0)

    def params(self) -> list[torch.Tensor]:
        return [*self.net.parameters(), self.log_s]

    def field(self, index: torch.Tensor | None = None):
        omega = self.omega if index is None else self.omega[index]
        scale = self.log_s.exp()  # non-leaf: its gradient reaches log_s through the graph

        def f(t, y):
            return omega[:, None] * (y @ self.j.T) + scale * self.net(y)

        return f


class GraphField:
    """A message-passing field on `[B, N, D]` node states: messages φ(x_i, x_j) along the
    edges (senders → receivers), summed per receiver, and ẋ_i = ω·J x_i + ψ(x_i, m_i)."""

    def __init__(self, batch: int, nodes: int = 5, dim: int = 2):
        self.phi = _mlp_in(2 * dim, dim, seed=1)
        self.psi = _mlp_in(2 * dim, dim, seed=2)
        ring = torch.arange(nodes)
        self.senders = torch.cat([ring, ring, torch.tensor([0, 2])])
        self.receivers = torch.cat([(ring + 1) % nodes, (ring - 1) % nodes,
                                    torch.tensor([3, 4])])
        self.j = _rotation(dim, 4.0)
        self.nodes = nodes

    def params(self) -> list[torch.Tensor]:
        return [*self.phi.parameters(), *self.psi.parameters()]

    def field(self):
        def f(t, x):  # x: (B, N, D)
            x_i, x_j = x[:, self.receivers], x[:, self.senders]  # (B, E, D)
            m = torch.zeros_like(x).index_add_(1, self.receivers,
                                               self.phi(torch.cat([x_i, x_j], -1)))
            return x @ self.j.T + 0.5 * self.psi(torch.cat([x, m], -1))

        return f


def _mlp_in(inputs: int, outputs: int, seed: int) -> torch.nn.Module:
    torch.manual_seed(seed)
    return torch.nn.Sequential(torch.nn.Linear(inputs, 16), torch.nn.Tanh(),
                               torch.nn.Linear(16, outputs)).to(F64)


def _gradients(field, y0: torch.Tensor, ts: torch.Tensor, weight: torch.Tensor, **options):
    """`(solution, gradients of a weighted sum of the outputs w.r.t. y0 and the params)`."""
    sol = solve(field.field(), y0, ts, rtol=1e-8, atol=1e-10, **options)
    loss = (torch.nan_to_num(sol.ys) * weight).sum()
    return sol, torch.autograd.grad(loss, [y0, *field.params()])


def _assert_same(got, want):
    for g, w in zip(got, want, strict=True):
        scale = w.abs().max().clamp_min(1e-300)
        assert float((g - w).abs().max() / scale) <= 1e-10


def _inputs(shape, n_out: int, t_end: float):
    gen = torch.Generator().manual_seed(0)
    y0 = torch.randn(*shape, generator=gen, dtype=F64, requires_grad=True)
    weight = torch.randn(shape[0], n_out, *shape[1:], generator=gen, dtype=F64)
    return y0, torch.linspace(0.0, t_end, n_out, dtype=F64), weight


ADAPTIVE = {
    "tsit5": {},
    "tsit5-pi": {"controller": "pi"},
    "dopri5-pi-tstops": {"method": "dopri5", "controller": "pi", "tstops": [0.9, 1.7]},
}


@pytest.mark.parametrize("case", ADAPTIVE)
@pytest.mark.parametrize("checkpoints", [2, 16])
def test_mlp_field_gradients_equal_plain_backprop(case, checkpoints):
    """Tens to hundreds of steps; few checkpoints (2) thin often and rerun steps many times."""
    field = MLPField(batch=3)
    y0, ts, weight = _inputs((3, 4), 9, 3.0)
    plain, want = _gradients(field, y0, ts, weight, **ADAPTIVE[case])
    sol, got = _gradients(field, y0, ts, weight, checkpoints=checkpoints, **ADAPTIVE[case])
    assert 50 <= int(plain.stats["n_steps"].max()) <= 500
    assert torch.equal(sol.ys, plain.ys)
    _assert_same(got, want)


@pytest.mark.parametrize("case", ["tsit5", "dopri5-pi-tstops"])
def test_graph_field_gradients_equal_plain_backprop(case):
    field = GraphField(batch=2)
    y0, ts, weight = _inputs((2, 5, 2), 7, 2.0)
    plain, want = _gradients(field, y0, ts, weight, **ADAPTIVE[case])
    _, got = _gradients(field, y0, ts, weight, checkpoints=4, **ADAPTIVE[case])
    assert int(plain.stats["n_steps"].max()) >= 30
    _assert_same(got, want)


@pytest.mark.parametrize("compact", [False, True])
def test_samples_with_different_step_counts(compact):
    """ω from 1 to 8 across 16 samples: their step counts differ several-fold; with
    `restrict` the solve compacts (restarts on the samples still running) as it goes."""
    batch = 16
    field = MLPField(batch, omega=torch.linspace(1.0, 8.0, batch).tolist())
    y0, ts, weight = _inputs((batch, 4), 6, 1.5)
    restrict = (lambda index: field.field(index)) if compact else None
    plain, want = _gradients(field, y0, ts, weight, restrict=restrict)
    sol, got = _gradients(field, y0, ts, weight, restrict=restrict, checkpoints=3)
    steps = plain.stats["n_steps"]
    assert int(steps.max()) >= 5 * int(steps.min()) and int(steps.min()) >= 20
    assert torch.equal(sol.stats["n_steps"], steps)
    _assert_same(got, want)


FIXED = {
    "tsit5": {"fixed_dt": 0.02},
    "rk4-tstops": {"method": "rk4", "fixed_dt": 0.02, "tstops": [0.77]},
}


@pytest.mark.parametrize("case", FIXED)
def test_fixed_steps_gradients_equal_plain_backprop(case):
    for field, shape in ((MLPField(batch=3), (3, 4)), (GraphField(batch=2), (2, 5, 2))):
        y0, ts, weight = _inputs(shape, 5, 2.0)
        plain, want = _gradients(field, y0, ts, weight, **FIXED[case])
        _, got = _gradients(field, y0, ts, weight, checkpoints=5, **FIXED[case])
        assert int(plain.stats["n_steps"].max()) == 100 + ("tstops" in case)
        _assert_same(got, want)


def test_random_draws_in_f_are_replayed():
    """f draws noise from torch's generator (as dropout would): the reruns draw the same."""
    field = MLPField(batch=2)

    def noisy_field():
        base = field.field()
        return lambda t, y: base(t, y) + 1e-3 * torch.randn(y.shape, dtype=F64)

    noisy = MLPField(batch=2)
    noisy.params, noisy.field = field.params, noisy_field
    y0, ts, weight = _inputs((2, 4), 5, 1.0)
    torch.manual_seed(5)
    _, want = _gradients(noisy, y0, ts, weight, fixed_dt=0.02)
    torch.manual_seed(5)
    _, got = _gradients(noisy, y0, ts, weight, fixed_dt=0.02, checkpoints=3)
    _assert_same(got, want)


def test_backward_fills_grad_as_plain_backprop_does():
    """`loss.backward()` (training's way) rather than `autograd.grad`."""
    field = GraphField(batch=2)
    y0, ts, weight = _inputs((2, 5, 2), 5, 1.0)
    grads = []
    for options in ({}, {"checkpoints": 4}):
        for p in field.params():
            p.grad = None
        sol = solve(field.field(), y0, ts, rtol=1e-8, atol=1e-10, **options)
        (sol.ys * weight).sum().backward()
        grads.append([p.grad.clone() for p in field.params()])
    _assert_same(grads[1], grads[0])


def test_a_second_backward_pass_recomputes_again():
    field = MLPField(batch=2)
    y0, ts, weight = _inputs((2, 4), 5, 2.0)
    sol = solve(field.field(), y0, ts, rtol=1e-8, atol=1e-10, checkpoints=3)
    loss = (sol.ys * weight).sum()
    first = torch.autograd.grad(loss, [y0], retain_graph=True)
    second = torch.autograd.grad(loss, [y0])
    _, want = _gradients(field, y0, ts, weight)
    _assert_same(first, want[:1])
    _assert_same(second, want[:1])


def _peak_bytes(run) -> int:
    """The most bytes torch held at once while `run()` ran, above what it held before
    (torch's profiler: every CPU allocation and free, in order)."""
    with profile(activities=[ProfilerActivity.CPU], profile_memory=True) as prof:
        run()
    events = sorted((e for e in prof.profiler.kineto_results.events()
                     if e.name() == "[memory]"), key=lambda e: e.start_ns())
    return max(itertools.accumulate(e.nbytes() for e in events))


def _saved_after_forward(field, y0, ts, **options) -> int:
    """Bytes of the tensors autograd keeps for the backward pass once the solve is done
    (saved-tensor hooks around it: a checkpointed step's own hooks hand autograd handles)."""
    storages: dict[int, int] = {}

    def pack(x):
        storages[x.untyped_storage().data_ptr()] = x.untyped_storage().nbytes()
        return x

    with torch.autograd.graph.saved_tensors_hooks(pack, lambda x: x):
        solve(field.field(), y0, ts, rtol=1e-6, atol=1e-8, **options)
    return sum(storages.values())


def test_memory_stays_flat_as_the_steps_grow_tenfold():
    """A wider MLP (hidden 64), horizons 1 and 10: plain backprop's peak grows with the
    steps, the checkpointed solve's (16 checkpoints) barely moves."""
    field = MLPField(batch=8, features=8)
    field.net = _mlp(8, 64, seed=0)
    gen = torch.Generator().manual_seed(1)
    y0 = torch.randn(8, 8, generator=gen, dtype=F64, requires_grad=True)
    peaks, saved, steps = {}, {}, {}
    for horizon, options in itertools.product((1.0, 10.0), ({}, {"checkpoints": 16})):
        ts = torch.linspace(0.0, horizon, 11, dtype=F64)

        def run(ts=ts, options=options, horizon=horizon):
            sol = solve(field.field(), y0, ts, rtol=1e-6, atol=1e-8, **options)
            steps[horizon] = int(sol.stats["n_steps"].max())
            sol.ys.square().sum().backward()

        key = (horizon, bool(options))
        peaks[key] = _peak_bytes(run)
        saved[key] = _saved_after_forward(field, y0, ts, **options)
    assert steps[10.0] >= 8 * steps[1.0]
    assert peaks[(10.0, False)] >= 6 * peaks[(1.0, False)]
    assert peaks[(10.0, True)] <= 1.5 * peaks[(1.0, True)], peaks
    assert peaks[(10.0, True)] * 15 <= peaks[(10.0, False)], peaks
    assert saved[(10.0, False)] >= 6 * saved[(1.0, False)]
    assert saved[(10.0, True)] == saved[(1.0, True)], saved


def _reversed_loop(n: int, checkpoints: int):
    """A loop of n steps x ← tanh(W x) through `Checkpointed`, differentiated: (its
    gradient w.r.t. W, the plain loop's, the steps it reran)."""
    gen = torch.Generator().manual_seed(0)
    w = (0.5 * torch.randn(6, 6, generator=gen, dtype=F64)).requires_grad_()
    x0 = torch.randn(6, generator=gen, dtype=F64)

    def step(carry):
        return (torch.tanh(w @ carry[0]),), None

    def run(step):
        carry = (x0,)
        for _ in range(n):
            carry, _ = step(carry)
        return torch.autograd.grad(carry[0].square().sum(), w)[0]

    looped = checkpoint.Checkpointed(step, checkpoints)
    return run(looped), run(step), looped.reruns


@pytest.mark.parametrize("checkpoints", [1, 4, 16])
def test_reruns_stay_within_revolves_bound(checkpoints):
    """Each step runs at most r + 1 more times, r the smallest with C(C + 1 + r, r) ≥ L,
    L = 2·N/C the most steps between two kept states; with C = 16 and N = 200 that is
    r = 1: one run to move on, one to keep its tensors."""
    n = 200
    got, want, reruns = _reversed_loop(n, checkpoints)
    assert torch.equal(got, want)
    span = max(1, 2 * n // checkpoints)
    r = next(r for r in itertools.count(1) if math.comb(checkpoints + 1 + r, r) >= span)
    assert reruns <= (r + 1) * n + 1, (reruns, r)  # + 1: the first step's extra run
    if checkpoints == 16:
        assert reruns <= 2 * n + 1


def test_advance_length_follows_the_binomial_rule():
    """The split leaves each part within what its states and runs can reverse."""
    for steps, snapshots in itertools.product(range(2, 80), range(2, 7)):
        m = checkpoint.advance_length(steps, snapshots)
        r = next(r for r in itertools.count(1) if math.comb(snapshots + r, r) >= steps)
        assert 1 <= m <= steps - 1
        assert m <= math.comb(snapshots + r - 1, r - 1)
        assert steps - m <= math.comb(snapshots - 1 + r, r)


def test_a_right_hand_side_that_changes_is_refused():
    """f that doubles once the forward pass is over, or returns NaN then: the reruns take
    other steps, and the backward pass says so instead of returning a wrong gradient."""
    field = MLPField(batch=2)
    y0, ts, weight = _inputs((2, 4), 5, 2.0)
    base, after = field.field(), {"forward": True}

    def f(t, y):
        out = base(t, y)
        return out if after["forward"] else after["change"](out)

    for change in (lambda out: 2.0 * out, lambda out: out * math.nan):
        after["forward"] = True
        sol = solve(f, y0, ts, rtol=1e-8, atol=1e-10, checkpoints=3)
        after.update(forward=False, change=change)
        with pytest.raises(RuntimeError, match="must compute the same values"):
            torch.autograd.grad((sol.ys * weight).sum(), [y0])


class _Scale(torch.autograd.Function):
    """y · w as a custom autograd.Function."""

    @staticmethod
    def forward(ctx, y, w):
        ctx.save_for_backward(y, w)
        return y * w

    @staticmethod
    def backward(ctx, g):
        y, w = ctx.saved_tensors
        return g * w, (g * y).sum()


def test_tensors_f_takes_from_outside_get_their_gradients():
    """Through a custom autograd.Function too; and one hidden from torch functions
    (`DisableTorchFunction`) is refused rather than left without a gradient."""
    field = MLPField(batch=2)
    y0, ts, weight = _inputs((2, 4), 5, 1.0)
    log_w = torch.tensor(0.5, dtype=F64, requires_grad=True)
    grads = []
    for options in ({}, {"checkpoints": 2}):
        w, base = log_w.exp(), field.field()  # w: non-leaf, made outside f
        sol = solve(lambda t, y, w=w, base=base: _Scale.apply(base(t, y), w), y0, ts,
                    **options)
        grads.append(torch.autograd.grad((sol.ys * weight).sum(), [log_w, y0]))
    _assert_same(grads[1], grads[0])

    w, base = log_w.exp(), field.field()

    def hidden(t, y):
        with torch._C.DisableTorchFunction():
            return base(t, y) * w

    with pytest.raises(RuntimeError, match="without passing it to a torch function"):
        solve(hidden, y0, ts, checkpoints=2)


def test_options():
    field = MLPField(batch=2)
    y0, ts, _ = _inputs((2, 4), 5, 1.0)
    for bad in (0, -3, 2.5, True):
        with pytest.raises(ValueError, match="checkpoints must be a positive integer"):
            solve(field.field(), y0, ts, checkpoints=bad)
    with pytest.raises(ValueError, match="fused steps"):
        solve(field.field(), y0, ts, checkpoints=2, fused=False)
    with torch.no_grad():  # nothing recorded: a plain solve, the same numbers
        plain = solve(field.field(), y0, ts)
        assert torch.equal(solve(field.field(), y0, ts, checkpoints=2).ys, plain.ys)
