"""Compaction (`solve(..., restrict=...)`): once most samples have finished, the solve goes on
with the running ones only. Held to the same samples solved alone (batch of 1), to closed
forms, to the uncompacted solve's step counts and statuses, and, for gradients, to the
uncompacted solve's and to finite differences (gradcheck); and, for the neural ODEs, a
rollout to the one without compaction and an ensemble's member to the member alone."""

from __future__ import annotations

import importlib
import math

import pytest
import torch
from conftest import rounding_apart
from torch import nn

from mpnode_cli.solver import Status, solve
from mpnode_cli.solver.options import SolverOptions

solve_module = importlib.import_module("mpnode_cli.solver.solve")


@pytest.fixture
def restarts(monkeypatch):
    """The number of adaptive solves each `solve` ran (1: no compaction), in a list."""
    counts = []
    inner = solve_module.solve_adaptive

    def counting(*args, **kwargs):
        counts.append(1)
        return inner(*args, **kwargs)

    monkeypatch.setattr(solve_module, "solve_adaptive", counting)
    return counts


def decay(rate: torch.Tensor):
    """dy/dt = −λ_b·y, per sample; `restrict` gives the samples' own rates."""
    def f(t, y):
        return -rate[:, None] * y

    return f, lambda index: decay(rate[index])[0]


def rates(batch: int) -> torch.Tensor:
    return torch.logspace(0, 3, batch, dtype=torch.float64)  # λ from 1 to 1000


@pytest.mark.parametrize("fused", [True, False])
def test_each_sample_equals_the_sample_solved_alone(fused, restarts):
    batch = 32
    lam = rates(batch)
    y0 = torch.linspace(0.5, 2.0, batch, dtype=torch.float64)[:, None].repeat(1, 3)
    ts = torch.linspace(0.0, 1.0, 11, dtype=torch.float64)
    f, restrict = decay(lam)
    sol = solve(f, y0, ts, restrict=restrict, fused=fused, rtol=1e-8, atol=1e-10)
    assert len(restarts) >= 3  # it compacted (twice at least: 32 → 16 → 8 rows)
    plain = solve(f, y0, ts, fused=fused, rtol=1e-8, atol=1e-10)
    assert bool(sol.success.all())
    for name in sol.stats:  # the same steps, and the same evaluations, for every sample
        assert torch.equal(sol.stats[name], plain.stats[name]), name
    exact = y0[:, None, :] * torch.exp(-lam[:, None, None] * ts[None, :, None])
    torch.testing.assert_close(sol.ys, exact, rtol=1e-6, atol=1e-9)
    for i in (0, 10, 20, 31):
        alone = solve(decay(lam[i : i + 1])[0], y0[i : i + 1], ts, fused=fused, rtol=1e-8,
                      atol=1e-10)
        assert alone.stats["n_steps"][0] == sol.stats["n_steps"][i]
        torch.testing.assert_close(sol.ys[i], alone.ys[0], rtol=1e-12, atol=1e-15)


def lorenz(t, y):
    x, yy, z = y.unbind(-1)
    return torch.stack((10 * (yy - x), x * (28 - z) - yy, x * yy - 8 / 3 * z), -1)


def test_lorenz_from_different_states_matches_scipy_and_the_uncompacted_solve(restarts):
    from scipy.integrate import solve_ivp

    gen = torch.Generator().manual_seed(0)
    batch = 24
    y0 = torch.randn(batch, 3, generator=gen, dtype=torch.float64) * 8 + torch.tensor(
        [0.0, 0.0, 25.0], dtype=torch.float64)
    # Different horizons' worth of stiffness: some samples are slowed down in time.
    speed = torch.linspace(0.05, 1.0, batch, dtype=torch.float64)

    def field(s):
        return lambda t, y: s[:, None] * lorenz(t, y)

    ts = torch.linspace(0.0, 1.5, 16, dtype=torch.float64)
    options = {"rtol": 1e-10, "atol": 1e-12}
    sol = solve(field(speed), y0, ts, restrict=lambda i: field(speed[i]), **options)
    n = len(restarts)
    assert n >= 2
    plain = solve(field(speed), y0, ts, compact=False, restrict=lambda i: field(speed[i]),
                  **options)
    assert len(restarts) == n + 1  # compact=False: one solve
    assert torch.equal(sol.stats["n_steps"], plain.stats["n_steps"])
    assert torch.equal(sol.stats["n_accepted"], plain.stats["n_accepted"])
    # Compaction changes the batch the field is evaluated on, so rounding may differ; Lorenz
    # is chaotic (largest Lyapunov exponent ≈ 0.9, so growth ≤ e^{0.9·1.5} ≈ 4 here) on
    # states up to ~50.
    bound = rounding_apart(plain.stats["n_steps"][:, None, None], 50 * math.exp(0.9 * 1.5))
    assert bool(((sol.ys - plain.ys).abs() <= bound).all())
    for i in (0, batch - 1):
        ref = solve_ivp(lambda t, y, s=float(speed[i]): s * lorenz(t, torch.tensor(y)).numpy(),
                        (0.0, 1.5),
                        y0[i].numpy(), method="DOP853", t_eval=ts.numpy(), rtol=1e-13,
                        atol=1e-14).y.T
        torch.testing.assert_close(sol.ys[i], torch.tensor(ref), rtol=1e-6, atol=1e-6)


def test_compact_false_and_no_restrict_run_one_solve(restarts):
    lam = rates(32)
    f, restrict = decay(lam)
    y0 = torch.ones(32, 1, dtype=torch.float64)
    solve(f, y0, [0.0, 1.0], restrict=restrict, compact=False)
    solve(f, y0, [0.0, 1.0])
    solve(f, y0, [0.0, 1.0], restrict=restrict, fixed_dt=0.01)
    assert len(restarts) == 2  # the fixed-step solve is not adaptive
    solve(f, y0, [0.0, 1.0], restrict=restrict, restrict_block=5)  # 32 rows, no blocks of 5
    assert len(restarts) == 3
    assert SolverOptions().solve_kwargs()["compact"] is True


def test_blocks_are_kept_whole():
    batch, block = 32, 4
    lam = rates(batch).view(-1, block).flip(1).reshape(-1)  # each block: fast to slow
    given = []
    f, restrict = decay(lam)

    def spy(index):
        given.append(index)
        return restrict(index)

    y0 = torch.ones(batch, 2, dtype=torch.float64)
    ts = torch.linspace(0.0, 1.0, 5, dtype=torch.float64)
    sol = solve(f, y0, ts, restrict=spy, restrict_block=block)
    assert given
    for index in given:
        blocks = index.view(-1, block)
        assert torch.equal(blocks - blocks[:, :1], torch.arange(block).expand_as(blocks))
        assert bool((blocks[:, 0] % block == 0).all())
    plain = solve(f, y0, ts)
    assert torch.equal(sol.stats["n_steps"], plain.stats["n_steps"])
    torch.testing.assert_close(sol.ys, plain.ys, rtol=1e-12, atol=1e-15)


def blowing_up(rate: torch.Tensor, blow: torch.Tensor):
    """dy/dt = −λ·y, or y² where `blow` (y(0) = 1: singular at t = 1)."""
    def f(t, y):
        return torch.where(blow[:, None], y * y, -rate[:, None] * y)

    return f, lambda index: blowing_up(rate[index], blow[index])[0]


def test_failures_and_tstops_keep_their_statuses_and_outputs(restarts):
    batch = 32
    lam = rates(batch)
    blow = torch.zeros(batch, dtype=torch.bool)
    blow[[2, 20, 31]] = True  # 20 and 31 fail after most others have finished
    y0 = torch.ones(batch, 1, dtype=torch.float64)
    ts = torch.linspace(0.0, 2.0, 21, dtype=torch.float64)
    stops = [0.3, 1.234, 1.5]
    f, restrict = blowing_up(lam, blow)
    sol = solve(f, y0, ts, restrict=restrict, tstops=stops, rtol=1e-8, atol=1e-10)
    assert len(restarts) >= 2
    plain = solve(f, y0, ts, tstops=stops, rtol=1e-8, atol=1e-10)
    assert sol.status.tolist() == plain.status.tolist()
    assert set(sol.status[blow].tolist()) <= {Status.NON_FINITE, Status.DT_UNDERFLOW}
    assert bool((sol.status[~blow] == Status.SUCCESS).all())
    for name in sol.stats:
        assert torch.equal(sol.stats[name], plain.stats[name]), name
    # The decays contract (growth 1, |y| ≤ 1); on the blow-ups y' = y² (y0 = 1) a deviation
    # grows by (y(t)/y(s))², so the bound scales as y(t)² there.
    size = plain.ys.abs().nan_to_num(0.0)
    bound = rounding_apart(plain.stats["n_steps"][:, None, None], (1 + size) ** 2)
    assert torch.equal(sol.ys.isnan(), plain.ys.isnan())
    assert bool(((sol.ys - plain.ys).abs().nan_to_num(0.0) <= bound).all())
    exact = torch.exp(-lam[~blow, None] * ts)
    torch.testing.assert_close(sol.ys[~blow, :, 0], exact, rtol=1e-5, atol=1e-9)
    before = ts < 0.95
    torch.testing.assert_close(sol.ys[20, before, 0], 1 / (1 - ts[before]), rtol=1e-5, atol=0)
    assert bool(torch.isnan(sol.ys[20, ts > 1.0, 0]).all())


class LinearField(nn.Module):
    """dy/dt = −λ_b·y + tanh(W y + b): per-sample stiffness and shared parameters."""

    def __init__(self, feat: int):
        super().__init__()
        torch.manual_seed(0)
        self.lin = nn.Linear(feat, feat).double()

    def field(self, lam):
        return lambda t, y: -lam[:, None] * y + torch.tanh(self.lin(y))


@pytest.mark.parametrize("fused", [True, False])
def test_gradients_equal_the_uncompacted_solves(fused, restarts):
    batch, feat = 32, 3
    lam = torch.logspace(0, 2, batch, dtype=torch.float64).requires_grad_()
    model = LinearField(feat)
    y0 = torch.randn(batch, feat, dtype=torch.float64, requires_grad=True)
    ts = torch.linspace(0.0, 1.0, 9, dtype=torch.float64)
    weight = torch.randn(batch, ts.numel(), feat, dtype=torch.float64)
    inputs = (y0, lam, *model.parameters())
    grads = []
    for compact in (True, False):
        sol = solve(model.field(lam), y0, ts, fused=fused, compact=compact,
                    restrict=lambda i: model.field(lam[i]), rtol=1e-6, atol=1e-9)
        grads.append(torch.autograd.grad((sol.ys * weight).sum(), inputs))
    assert len(restarts) >= 3  # the compacted solve restarted
    for got, want in zip(*grads, strict=True):
        torch.testing.assert_close(got, want, rtol=1e-10, atol=1e-12)


@pytest.mark.parametrize("fused", [True, False])
def test_gradcheck_where_compaction_triggers(fused, monkeypatch, restarts):
    import mpnode_cli.solver.adaptive as adaptive

    monkeypatch.setattr(adaptive, "COMPACT_MIN_DROP", 1)  # compact a batch of 4
    ts = torch.tensor([0.0, 0.1, 0.25], dtype=torch.float64)
    y0 = torch.tensor([[0.3, -0.7], [1.1, 0.2], [0.5, 0.5], [-0.4, 0.9]], dtype=torch.float64,
                      requires_grad=True)
    theta = torch.tensor([1.0, 3.0, 40.0, 90.0], dtype=torch.float64, requires_grad=True)

    def field(th):
        return lambda t, y: -th[:, None] * y + 0.5 * torch.sin(y) * y.flip(-1)

    def run(y0, theta):
        return solve(field(theta), y0, ts, restrict=lambda i: field(theta[i]), fused=fused,
                     rtol=1e-8, atol=1e-10).ys

    run(y0, theta)
    assert len(restarts) >= 2
    # fast_mode checks vᵀJu for random u, v (one backward, a directional difference)
    # instead of every entry of J: a wrong compacted gradient still shows in vᵀJu.
    assert torch.autograd.gradcheck(run, (y0, theta), eps=1e-6, atol=1e-6, rtol=1e-4,
                                    fast_mode=True)


def test_float32_compaction_is_the_same_solve_to_its_precision(restarts):
    lam = rates(32).float()
    f, restrict = decay(lam)
    y0 = torch.ones(32, 2)
    ts = torch.linspace(0.0, 1.0, 6)
    sol = solve(f, y0, ts, restrict=restrict, rtol=1e-5, atol=1e-7)
    assert len(restarts) >= 2 and sol.ys.dtype == torch.float32
    exact = torch.exp(-lam[:, None].double() * ts.double())
    assert math.isclose(float((sol.ys[..., 0].double() - exact).abs().max()), 0.0,
                        abs_tol=1e-5)
