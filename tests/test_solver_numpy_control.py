"""The adaptive step's small arithmetic in numpy (`mpnode_cli/solver/host.py`), which every
uncompiled CPU solve runs, against the same code in torch (`host.NUMPY_ON_CPU = False`):
the same steps, accepts, rejections, evaluations and statuses per sample, outputs to 1e-12
and gradients to 1e-10 in float64 (to rounding in float32), for both adaptive pairs and
both controllers, with tstops, several outputs crossed per step, failing samples and
compaction; the namespaces' pieces against each other; and a solve in numpy against a
closed form."""

from __future__ import annotations

import contextlib
import importlib
import math

import numpy as np
import pytest
import torch

from mpnode_cli.solver import Status, adaptive, host, solve
from mpnode_cli.solver.host import NumpyOps, TorchOps, ops_for

SWITCH = 0.37  # where the zero-order-hold input of `forced` changes
solve_module = importlib.import_module("mpnode_cli.solver.solve")


@contextlib.contextmanager
def torch_on_cpu():
    """Run the torch namespace on the CPU inside the block."""
    before = host.NUMPY_ON_CPU
    host.NUMPY_ON_CPU = False
    try:
        yield
    finally:
        host.NUMPY_ON_CPU = before


def forced(theta: torch.Tensor):
    """A nonlinear, damped field on `[B, 2, 2]` states with three parameters and a
    zero-order-hold input that jumps at `SWITCH`."""

    def f(t, y):
        u = torch.where(t < SWITCH, 1.0, -2.0).to(y.dtype)[:, None, None]
        return (-theta[0] * y + theta[1] * torch.sin(y) * y.flip(-1)
                + theta[2] * u * torch.cos(t).to(y.dtype)[:, None, None])

    return f


def both(run):
    """`run()` with the numpy namespace (the default on the CPU), then with torch's."""
    assert ops_for(torch.device("cpu"), compile=False) is NumpyOps
    got = run()
    with torch_on_cpu():
        want = run()
    return got, want


def assert_same_solve(got, want, rtol=1e-12, atol=1e-12):
    assert got.status.tolist() == want.status.tolist()
    for name in want.stats:
        assert torch.equal(got.stats[name], want.stats[name]), name
        assert got.stats[name].dtype == torch.int64
    assert got.status.dtype == torch.int64 and got.ys.dtype == want.ys.dtype
    torch.testing.assert_close(got.ys, want.ys, rtol=rtol, atol=atol, equal_nan=True)


CASES = {
    "tsit5-pi": ("tsit5", {"controller": "pi"}),
    "tsit5-i": ("tsit5", {"controller": "i"}),
    "dopri5-pi": ("dopri5", {"controller": "pi"}),
    "dopri5-i": ("dopri5", {"controller": "i"}),
    "tsit5-pi-tstops": ("tsit5", {"controller": "pi", "tstops": [SWITCH, 0.61]}),
    "tsit5-i-tstops": ("tsit5", {"controller": "i", "tstops": [SWITCH]}),
    "dopri5-pi-tstops-dt0": ("dopri5", {"controller": "pi", "tstops": [SWITCH], "dt0": 1e-3}),
}


def problem(dtype=torch.float64, batch=6):
    gen = torch.Generator().manual_seed(0)
    y0 = torch.randn(batch, 2, 2, generator=gen, dtype=dtype)
    theta = torch.tensor([0.8, 0.5, 0.3], dtype=dtype)
    return y0, theta


@pytest.mark.parametrize("fused", [True, False])
@pytest.mark.parametrize("case", CASES)
def test_numpy_and_torch_take_the_same_steps(case, fused):
    """61 outputs over [0, 2] at loose tolerances: each step crosses several of them."""
    method, options = CASES[case]
    y0, theta = problem()
    ts = torch.linspace(0.0, 2.0, 61, dtype=torch.float64)
    got, want = both(lambda: solve(forced(theta), y0, ts, method=method, rtol=1e-5,
                                   atol=1e-7, fused=fused, **options))
    assert bool((want.stats["n_accepted"] < 30).all())  # two outputs a step or more
    assert_same_solve(got, want)


@pytest.mark.parametrize("fused", [True, False])
@pytest.mark.parametrize("case", ["tsit5-pi", "dopri5-i", "tsit5-i-tstops"])
def test_gradients_agree(case, fused):
    method, options = CASES[case]
    y0, theta = problem()
    y0.requires_grad_()
    theta.requires_grad_()
    ts = torch.linspace(0.0, 1.0, 21, dtype=torch.float64)
    weight = torch.randn(ts.numel(), 2, 2, dtype=torch.float64,
                         generator=torch.Generator().manual_seed(1))

    def run():
        sol = solve(forced(theta), y0, ts, method=method, rtol=1e-7, atol=1e-9, fused=fused,
                    **options)
        return sol, torch.autograd.grad((sol.ys * weight).sum(), (y0, theta))

    (got, got_grads), (want, want_grads) = both(run)
    assert_same_solve(got, want)
    for g, w in zip(got_grads, want_grads, strict=True):
        torch.testing.assert_close(g, w, rtol=1e-10, atol=1e-10)


def test_float32_agrees_to_rounding():
    y0, theta = problem(torch.float32, batch=16)
    ts = torch.linspace(0.0, 2.0, 51, dtype=torch.float64)
    got, want = both(lambda: solve(forced(theta), y0, ts, rtol=1e-4, atol=1e-6,
                                   controller="i", tstops=[SWITCH]))
    assert got.ys.dtype == torch.float32
    assert_same_solve(got, want, rtol=1e-5, atol=1e-6)


def test_failing_samples_get_the_same_statuses():
    """A blow-up (y' = y², singular at t = 1: DT_UNDERFLOW), a field that is NaN after
    t = 0 (NON_FINITE after 20 rejections), a stiff one that runs out of steps
    (MAX_STEPS), a NaN initial state, and decaying samples that succeed."""
    status = [Status.DT_UNDERFLOW, Status.NON_FINITE, Status.MAX_STEPS, Status.NON_FINITE,
              Status.SUCCESS, Status.SUCCESS]
    kind = torch.tensor([0, 1, 2, 3, 3, 3])[:, None]
    y0 = torch.tensor([[1.0], [1.0], [1.0], [math.nan], [1.0], [2.0]], dtype=torch.float64)

    def f(t, y):
        nan = torch.where(t[:, None] > 0, math.nan, y)
        return torch.where(kind == 0, y * y, torch.where(
            kind == 1, nan, torch.where(kind == 2, -5000.0 * y, -y)))

    ts = torch.linspace(0.0, 2.0, 21, dtype=torch.float64)
    got, want = both(lambda: solve(f, y0, ts, rtol=1e-8, atol=1e-10, max_steps=1000))
    assert want.status.tolist() == status
    assert_same_solve(got, want, rtol=1e-8)  # y ≈ 1e8 by t = 1, from cancelling sums
    torch.testing.assert_close(got.ys[1:], want.ys[1:], rtol=1e-12, atol=1e-12, equal_nan=True)


def decay(rate: torch.Tensor):
    """dy/dt = −λ_b·y; `restrict` gives the samples' own rates."""
    def f(t, y):
        return -rate[:, None] * y

    return f, lambda index: decay(rate[index])[0]


@pytest.mark.parametrize("block", [1, 4])
def test_compaction_agrees(block, monkeypatch):
    batch = 32
    rate = torch.logspace(0, 3, batch, dtype=torch.float64)
    y0 = torch.linspace(0.5, 2.0, batch, dtype=torch.float64)[:, None].repeat(1, 3)
    ts = torch.linspace(0.0, 1.0, 11, dtype=torch.float64)
    f, restrict = decay(rate)
    restarts = []
    inner = solve_module.solve_adaptive

    def counting(*args, **kwargs):
        restarts.append(1)
        return inner(*args, **kwargs)

    monkeypatch.setattr(solve_module, "solve_adaptive", counting)
    got, want = both(lambda: solve(f, y0, ts, restrict=restrict, restrict_block=block,
                                   rtol=1e-8, atol=1e-10, tstops=[0.45]))
    assert len(restarts) >= 4  # each of the two compacted at least once
    assert_same_solve(got, want)
    exact = y0[:, None, :] * torch.exp(-rate[:, None, None] * ts[None, :, None])
    torch.testing.assert_close(got.ys, exact, rtol=1e-6, atol=1e-9)


def test_a_linear_ode_matches_its_closed_form():
    """y' = λ·y + sin(ωt), scalar per sample, in the numpy namespace (the CPU default):
    y(t) = e^{λt}·(y₀ + ω/(λ² + ω²)) − (λ·sin ωt + ω·cos ωt)/(λ² + ω²)."""
    lam = torch.tensor([-3.0, -1.0, -0.2, 0.0, 0.5], dtype=torch.float64)
    omega = 2.0
    y0 = torch.tensor([1.0, -2.0, 0.5, 1.5, 0.1], dtype=torch.float64)[:, None]
    ts = torch.linspace(0.0, 3.0, 31, dtype=torch.float64)
    sol = solve(lambda t, y: lam[:, None] * y + torch.sin(omega * t)[:, None], y0, ts,
                rtol=1e-10, atol=1e-12)
    assert bool(sol.success.all())
    d = lam[:, None] ** 2 + omega**2
    wt = omega * ts[None, :]
    exact = (torch.exp(lam[:, None] * ts) * (y0 + omega / d)
             - (lam[:, None] * torch.sin(wt) + omega * torch.cos(wt)) / d)
    torch.testing.assert_close(sol.ys[..., 0], exact, rtol=1e-8, atol=1e-9)


def test_the_namespace_is_chosen_by_device_compile_and_the_switch():
    cpu, cuda = torch.device("cpu"), torch.device("cuda")
    assert ops_for(cpu, compile=False) is NumpyOps
    assert ops_for(cpu, compile=True) is TorchOps  # the compiled step is tensor code
    assert ops_for(cuda, compile=False) is TorchOps
    with torch_on_cpu():
        assert ops_for(cpu, compile=False) is TorchOps


def test_state_dtypes_are_the_same_in_both():
    """Every field of the loop's `State` and `Attempt` after each step: float64 time, step
    and history, int64 counters, bool masks, the same in numpy as in torch."""
    seen = {}
    inner = adaptive.control

    def spy(*args):
        state, flags, step = inner(*args)
        key = host.NUMPY_ON_CPU
        fields = {**state._asdict(), **{f"attempt.{k}": v for k, v in step._asdict().items()
                                        if isinstance(v, torch.Tensor)}}
        seen.setdefault(key, set()).add(tuple((k, v.dtype, tuple(v.shape))
                                              for k, v in fields.items()))
        assert [int(x) for x in flags.tolist()] == flags.tolist()
        return state, flags, step

    adaptive.control = spy
    try:
        y0, theta = problem(torch.float32)
        both(lambda: solve(forced(theta), y0, [0.0, 0.5, 1.0], tstops=[SWITCH]))
    finally:
        adaptive.control = inner
    assert len(seen[True]) == 1 and seen[True] == seen[False]
    dtypes = dict((k, d) for k, d, _ in next(iter(seen[True])))
    assert dtypes["t"] == dtypes["dt"] == dtypes["err_prev"] == torch.float64
    assert dtypes["n_steps"] == dtypes["out_idx"] == torch.int64
    assert dtypes["running"] == dtypes["attempt.accept"] == torch.bool


def arrays(*xs):
    return [x.numpy() for x in xs]


def test_the_namespaces_pieces_agree():
    gen = torch.Generator().manual_seed(0)
    x32 = torch.randn(64, 18, generator=gen)
    x32[0, 0] = 1e20  # its square overflows float32: r = inf in both (a non-finite error)
    x64 = torch.randn(64, 30, generator=gen, dtype=torch.float64)
    for x in (x32, x64):
        r_t, r_n = TorchOps.rms(x), torch.from_numpy(NumpyOps.rms(x.numpy()))
        assert r_n.dtype == r_t.dtype == torch.float64
        torch.testing.assert_close(r_n, r_t, rtol=2e-7 if x is x32 else 1e-15, atol=0)
    assert math.isinf(TorchOps.rms(x32)[0]) and math.isinf(NumpyOps.rms(x32.numpy())[0])

    ts = torch.linspace(0.0, 1.0, 11, dtype=torch.float64)
    v = torch.tensor([-1.0, 0.0, 0.05, 0.1, 0.55, 1.0, 2.0], dtype=torch.float64)
    assert NumpyOps.searchsorted(*arrays(ts, v)).tolist() == TorchOps.searchsorted(ts, v).tolist()

    theta = torch.rand(16, 3, generator=gen, dtype=torch.float64)
    interp_t = torch.randn(7, 4, generator=gen, dtype=torch.float64)
    coef = NumpyOps.interpolant(*arrays(theta, interp_t))
    assert coef.shape == (16, 3, 7) and coef.flags.c_contiguous
    torch.testing.assert_close(torch.from_numpy(coef), TorchOps.interpolant(theta, interp_t),
                               rtol=1e-15, atol=1e-15)

    hk = torch.randn(7, 16, 5, generator=gen, dtype=torch.float64)
    y = torch.randn(16, 5, generator=gen, dtype=torch.float64)
    c = torch.from_numpy(coef)
    torch.testing.assert_close(NumpyOps.lanes(c, hk, y), TorchOps.lanes(c, hk, y), rtol=1e-14,
                               atol=1e-14)
    out_t, out_n = torch.zeros(16 * 3 + 1, 5, dtype=torch.float64), torch.zeros(16 * 3 + 1, 5,
                                                                                dtype=torch.float64)
    rows = torch.randperm(16 * 3, generator=gen)
    TorchOps.write_lanes(out_t, rows, c, hk, y)
    NumpyOps.write_lanes(out_n, rows, c, hk, y)
    torch.testing.assert_close(out_n, out_t, rtol=1e-14, atol=1e-14)

    mask = torch.tensor([False, True, False])
    count = torch.tensor([0, 3, 1])
    none = torch.zeros(3, dtype=torch.bool)
    want = TorchOps.flags(mask, count, none, mask, count.sum()).tolist()
    assert want == [1, 3, 0, 1, 4]
    assert NumpyOps.flags(*arrays(mask, count, none, mask), count.numpy().sum()).tolist() == want
    a = np.array([-1.0, 0.5, 2.0])
    assert NumpyOps.clip(a, 0.0, 1.0).tolist() == [0.0, 0.5, 1.0]
    assert NumpyOps.clip(a, None, 1.0).tolist() == [-1.0, 0.5, 1.0]
