"""The dense output's numpy form (`mpnode_cli/solver/dense.py`), which every uncompiled CPU
solve takes, against its torch form (`dense.NUMPY_ON_CPU = False`): the same steps,
accepts, rejections, evaluations and statuses per sample (equal: only the outputs' weights
and sums differ, and the step never reads them), outputs within the rounding bound of
their dense sums (`dense_rounding_bound`: it scales with the state's size and holds on any
CPU and BLAS) and gradients to 1e-10 in float64, for both adaptive pairs and
both controllers, with tstops, several outputs crossed per step, failing samples and
compaction; the two forms' pieces against each other; and a solve against a closed
form."""

from __future__ import annotations

import contextlib
import importlib
import math

import pytest
import torch

from mpnode_cli.solver import Status, dense, solve
from mpnode_cli.solver.dense import on_host
from mpnode_cli.solver.tableau import METHODS

SWITCH = 0.37  # where the zero-order-hold input of `forced` changes
solve_module = importlib.import_module("mpnode_cli.solver.solve")


@contextlib.contextmanager
def torch_on_cpu():
    """Run the dense output's torch form on the CPU inside the block."""
    before = dense.NUMPY_ON_CPU
    dense.NUMPY_ON_CPU = False
    try:
        yield
    finally:
        dense.NUMPY_ON_CPU = before


def forced(theta: torch.Tensor):
    """A nonlinear, damped field on `[B, 2, 2]` states with three parameters and a
    zero-order-hold input that jumps at `SWITCH`."""

    def f(t, y):
        u = torch.where(t < SWITCH, 1.0, -2.0).to(y.dtype)[:, None, None]
        return (-theta[0] * y + theta[1] * torch.sin(y) * y.flip(-1)
                + theta[2] * u * torch.cos(t).to(y.dtype)[:, None, None])

    return f


def both(run):
    """`run()` with the numpy form (the default on the CPU), then with torch's."""
    assert on_host(torch.device("cpu"), compile=False)
    got = run()
    with torch_on_cpu():
        want = run()
    return got, want


def two_sums_apart(terms: int, magnitude, dtype=torch.float64):
    """How far two floating-point sums of the same `terms` numbers may differ when they are
    added in different orders or vector widths (numpy's against torch's): each is within
    γ_n·Σ|x_i| of the exact sum, γ_n = n·u/(1 − n·u) (Higham, *Accuracy and Stability of
    Numerical Algorithms*, 2nd ed., §4.2), so the two within twice that. `magnitude` is
    Σ|x_i| (a number or a tensor of them)."""
    u = torch.finfo(dtype).eps / 2
    return 2 * terms * u / (1 - terms * u) * magnitude


def dense_rounding_bound(method: str, largest_state, dtype=torch.float64):
    """How far the two forms' dense outputs may differ, taking the same steps.

    Both take bit for bit the same steps, stages and step ends: the stats, compared
    exactly, are decided by the same torch code in both. They differ only in how a dense output
    y(t₀ + θh) = y₀ + Σ_i b_i(θ)·h·k_i is formed: numpy's powers and matmul against torch's
    cumprod and bmm, whose order and vector width depend on the CPU and the BLAS. Each
    weight b_i(θ) = Σ_k P_ik θ^k is a sum of K products (θ^k itself k − 1 products), so
    within γ_{2K}·Σ_k |P_ik| of its exact value for θ ∈ [0, 1]; the output is a sum of
    s + 1 terms, within γ_{s+1}·(|y₀| + Σ_i |b_i(θ)|·|h·k_i|). With L = Σ_ik |P_ik| (389
    for Tsit5) and every |h·k_i| at most ρ·Y, Y the largest state the sample's field was
    evaluated at (`largest_state`), the two paths differ by at most

        two_sums_apart(s + 1 + 2K, (1 + L)·ρ·Y).

    ρ = 4: an accepted step's stage increment h·k_i is at most |hλ|·|y| ≤ 3.5·Y on a
    decaying or damped field (the methods' stability interval on the negative axis ends
    near −3.5), and on y' = y², where every k_i = y² > 0, below the step's own increment
    (measured 0.09·Y on the step that jumps the pole). The bound scales with the state's
    size and the method, not with one CPU's rounding.
    """
    tableau = METHODS[method]
    terms = len(tableau.b) + 1 + 2 * len(tableau.interp[0])
    spread = sum(abs(p) for row in tableau.interp for p in row)
    return two_sums_apart(terms, (1 + spread) * 4.0 * largest_state, dtype)


def recording(f, seen: torch.Tensor, ts: torch.Tensor | None = None):
    """`f`, noting in `seen` each sample's largest finite |y| the solve evaluated it at:
    `seen [B]`, or `seen [B, T]` with `ts`, where column j holds the calls before
    t_{j+1} (all calls for the last output)."""
    def g(t, y):
        size = torch.nan_to_num(y.abs().flatten(1).amax(-1), nan=0.0, posinf=0.0)  # (B,)
        if ts is None:
            seen.copy_(torch.maximum(seen, size.to(seen.dtype)))
        else:
            later = torch.cat([ts[1:], ts.new_full((1,), math.inf)])
            before = t[:, None] <= later[None, :]  # (B, T): this call precedes t_{j+1}
            seen.copy_(torch.maximum(seen, torch.where(before, size[:, None], 0.0)))
        return f(t, y)

    return g


def assert_same_steps(got, want):
    """The same statuses and counts of steps, accepts, rejections and evaluations: these
    are decided by the same code in both forms, so they are equal."""
    assert got.status.tolist() == want.status.tolist()
    for name in want.stats:
        assert torch.equal(got.stats[name], want.stats[name]), name
        assert got.stats[name].dtype == torch.int64
    assert got.status.dtype == torch.int64 and got.ys.dtype == want.ys.dtype


def assert_same_solve(got, want, bound: torch.Tensor):
    """The same steps, and outputs within `bound` (broadcast against `ys`) of each other,
    NaN where the other is NaN."""
    assert_same_steps(got, want)
    assert torch.equal(got.ys.isnan(), want.ys.isnan())
    gap = (got.ys - want.ys).abs().nan_to_num(0.0)
    assert bool((gap <= bound).all()), f"largest gap over its bound: {(gap / bound).max()}"


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
    seen = torch.zeros(len(y0), dtype=torch.float64)
    got, want = both(lambda: solve(recording(forced(theta), seen), y0, ts, method=method,
                                   rtol=1e-5, atol=1e-7, fused=fused, **options))
    assert bool((want.stats["n_accepted"] < 30).all())  # two outputs a step or more
    assert_same_solve(got, want, dense_rounding_bound(method, seen)[:, None, None, None])


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

    seen = torch.zeros(len(y0), dtype=torch.float64)

    def run():
        sol = solve(recording(forced(theta), seen), y0, ts, method=method, rtol=1e-7,
                    atol=1e-9, fused=fused, **options)
        return sol, torch.autograd.grad((sol.ys * weight).sum(), (y0, theta))

    (got, got_grads), (want, want_grads) = both(run)
    assert_same_solve(got, want, dense_rounding_bound(method, seen)[:, None, None, None])
    # The gradients differ as the outputs do, through the same weights b_i(θ): 1e-10 is
    # ~1e5 unit roundoffs of these O(1) sums, and far below their size.
    for g, w in zip(got_grads, want_grads, strict=True):
        torch.testing.assert_close(g, w, rtol=1e-10, atol=1e-10)


def test_float32_agrees_to_rounding():
    y0, theta = problem(torch.float32, batch=16)
    ts = torch.linspace(0.0, 2.0, 51, dtype=torch.float64)
    seen = torch.zeros(len(y0), dtype=torch.float64)
    got, want = both(lambda: solve(recording(forced(theta), seen), y0, ts, rtol=1e-4,
                                   atol=1e-6, controller="i", tstops=[SWITCH]))
    assert got.ys.dtype == torch.float32
    bound = dense_rounding_bound("tsit5", seen, torch.float32)[:, None, None, None]
    assert_same_solve(got, want, bound)


def test_failing_samples_get_the_same_statuses():
    """A blow-up (y' = y², singular at t = 1: DT_UNDERFLOW), a field that is NaN after
    t = 0 (NON_FINITE after 20 rejections), a stiff one that runs out of steps
    (MAX_STEPS), a NaN initial state, and decaying samples that succeed: the same statuses
    and step counts in both forms, and outputs within `dense_rounding_bound`.

    The blow-up's output at t = 1 (1.2e8) comes from the step that jumps the numerical
    pole, whose stages reach Y = 8e14: there the two paths may differ by ~9e3 and differed
    by 1.9 (1.7e-8 relative) on an AMD EPYC, where a bit-level bound failed. The decays'
    outputs (Y ≤ 2) are held to 2e-11, far inside the solve's own error there.
    """
    status = [Status.DT_UNDERFLOW, Status.NON_FINITE, Status.MAX_STEPS, Status.NON_FINITE,
              Status.SUCCESS, Status.SUCCESS]
    kind = torch.tensor([0, 1, 2, 3, 3, 3])[:, None]
    y0 = torch.tensor([[1.0], [1.0], [1.0], [math.nan], [1.0], [2.0]], dtype=torch.float64)
    ts = torch.linspace(0.0, 2.0, 21, dtype=torch.float64)

    def f(t, y):
        nan = torch.where(t[:, None] > 0, math.nan, y)
        return torch.where(kind == 0, y * y, torch.where(
            kind == 1, nan, torch.where(kind == 2, -5000.0 * y, -y)))

    seen = torch.zeros(6, len(ts), dtype=torch.float64)
    got, want = both(lambda: solve(recording(f, seen, ts), y0, ts, rtol=1e-8, atol=1e-10,
                                   max_steps=1000))
    assert want.status.tolist() == status
    # Each sample's steps are shorter than the output spacing until the pole (384 steps on
    # [0, 1] for the blow-up), so the step that holds output j ends before t_{j+1} and the
    # states its stages saw are in `seen[:, j]`; at the pole the window holds them all.
    bound = dense_rounding_bound("tsit5", seen)[..., None]  # (B, T, 1)
    assert_same_solve(got, want, bound)
    assert bound[4:].max() < 1e-10  # the decays' bound is far inside the solve's error


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
    # Decays: no state exceeds its initial one.
    assert_same_solve(got, want, dense_rounding_bound("tsit5", y0.abs().amax(-1))[:, None, None])
    exact = y0[:, None, :] * torch.exp(-rate[:, None, None] * ts[None, :, None])
    torch.testing.assert_close(got.ys, exact, rtol=1e-6, atol=1e-9)


def test_a_linear_ode_matches_its_closed_form():
    """y' = λ·y + sin(ωt), scalar per sample, with the numpy form (the CPU default):
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


def test_the_form_is_chosen_by_device_compile_and_the_switch():
    cpu, cuda = torch.device("cpu"), torch.device("cuda")
    assert on_host(cpu, compile=False)
    assert not on_host(cpu, compile=True)  # the compiled step is tensor code
    assert not on_host(cuda, compile=False)
    with torch_on_cpu():
        assert not on_host(cpu, compile=False)


def test_the_two_forms_pieces_agree():
    gen = torch.Generator().manual_seed(0)
    theta = torch.rand(16, 3, generator=gen, dtype=torch.float64)
    interp_t = torch.randn(7, 4, generator=gen, dtype=torch.float64)
    coef = dense.interpolant_numpy(theta, interp_t)
    assert coef.shape == (16, 3, 7) and coef.is_contiguous()
    # b_i(θ) = Σ_k P_ik θ^k: K products and their sum in each form (see
    # `dense_rounding_bound`), to γ_{2K}·Σ_k |P_ik|·θ^k each.
    size = interp_t.abs() @ (theta[..., None] ** torch.arange(1, 5)).reshape(-1, 4).T  # (s, B·W)
    apart = two_sums_apart(2 * 4, size.T.reshape(16, 3, 7))
    assert bool(((coef - dense.interpolant_weights(theta, interp_t)).abs() <= apart).all())

    hk = torch.randn(7, 16, 5, generator=gen, dtype=torch.float64)
    y = torch.randn(16, 5, generator=gen, dtype=torch.float64)
    # y + Σ_i c_i·hk_i: s + 1 terms, summed by numpy's matmul and by torch's einsum / bmm.
    apart = two_sums_apart(8, y.abs()[:, None] + torch.einsum("bws,sbf->bwf", coef.abs(),
                                                              hk.abs()))
    assert bool(((dense.host_lanes(coef, hk, y) - dense.lanes(coef, hk, y)).abs()
                 <= apart).all())
    out_t, out_n = (torch.zeros(16 * 3 + 1, 5, dtype=torch.float64) for _ in range(2))
    rows = torch.randperm(16 * 3, generator=gen)
    dense.write_lanes(out_t, rows, coef, hk, y, numpy=False)
    dense.write_lanes(out_n, rows, coef, hk, y, numpy=True)
    assert bool(((out_n - out_t)[rows].abs() <= apart.reshape(-1, 5)).all())
    assert not out_n[-1].any() and not out_t[-1].any()  # the row no lane names is untouched
