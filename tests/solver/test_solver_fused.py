"""Tests of the fused Runge–Kutta step (`mpnode_cli/solver/fused.py`): its hand-written
backward against autograd's, which records every op of the same step (`fused=False`), and
against finite differences (gradcheck), for every method, both step-size controllers, with
tstops and with fixed steps."""

from __future__ import annotations

import pytest
import torch

from mpnode_cli.solver import Status, solve

SWITCH = 0.37  # where the zero-order-hold input of `problem` changes

# (method, options): adaptive pairs under both controllers, with and without stops, and
# fixed steps (the only way to run RK4), with a stop too.
CASES = {
    "tsit5-i": ("tsit5", {"controller": "i"}),
    "tsit5-pi": ("tsit5", {"controller": "pi"}),
    "dopri5-i": ("dopri5", {"controller": "i"}),
    "dopri5-pi": ("dopri5", {"controller": "pi"}),
    "tsit5-i-tstops": ("tsit5", {"controller": "i", "tstops": [SWITCH]}),
    "tsit5-pi-tstops": ("tsit5", {"controller": "pi", "tstops": [SWITCH, 0.61]}),
    "dopri5-pi-tstops": ("dopri5", {"controller": "pi", "tstops": [SWITCH]}),
    "tsit5-fixed": ("tsit5", {"fixed_dt": 0.07}),
    "dopri5-fixed-tstops": ("dopri5", {"fixed_dt": 0.07, "tstops": [SWITCH]}),
    "rk4-fixed": ("rk4", {"fixed_dt": 0.05}),
    "rk4-fixed-tstops": ("rk4", {"fixed_dt": 0.05, "tstops": [SWITCH]}),
}


def problem(theta: torch.Tensor, jump: bool = True):
    """A nonlinear field on `[B, 2, 2]` states with three parameters, time-dependent, with a
    zero-order-hold input that jumps at `SWITCH` (which the tstops cases stop at), or not."""

    def f(t, y):
        u = torch.where((t < SWITCH) | (not jump), 1.0, -2.0).to(y.dtype)[:, None, None]
        return (-theta[0] * y + theta[1] * torch.sin(y) * y.flip(-1)
                + theta[2] * u * torch.cos(t).to(y.dtype)[:, None, None])

    return f


def gradients(fused: bool, method: str, options: dict, ts: torch.Tensor, y0, theta, weight):
    sol = solve(problem(theta), y0, ts, method=method, rtol=1e-7, atol=1e-9, fused=fused,
                **options)
    return sol, torch.autograd.grad((sol.ys * weight).sum(), (y0, theta))


@pytest.mark.parametrize("case", CASES)
def test_fused_backward_agrees_with_autograd(case):
    """The same solve, forward bit for bit, and gradients to 1e-10 in float64; 21 outputs
    over a few steps, so that steps cross several outputs each."""
    method, options = CASES[case]
    gen = torch.Generator().manual_seed(0)
    y0 = torch.randn(4, 2, 2, generator=gen, dtype=torch.float64, requires_grad=True)
    theta = torch.tensor([0.8, 0.5, 0.3], dtype=torch.float64, requires_grad=True)
    ts = torch.linspace(0.0, 1.0, 21, dtype=torch.float64)
    weight = torch.randn(4, 21, 2, 2, generator=gen, dtype=torch.float64)
    fused, grads = gradients(True, method, options, ts, y0, theta, weight)
    recorded, want = gradients(False, method, options, ts, y0, theta, weight)
    assert torch.equal(fused.ys, recorded.ys)
    for name in fused.stats:
        assert torch.equal(fused.stats[name], recorded.stats[name]), name
    for got, ref in zip(grads, want, strict=True):
        torch.testing.assert_close(got, ref, rtol=1e-10, atol=1e-10)


@pytest.mark.parametrize("case", CASES)
def test_fused_backward_passes_gradcheck(case):
    """Against finite differences: tight tolerances, so that a perturbed input takes the same
    steps (the controller is detached, as in `test_gradcheck_through_the_solve`), and the
    input jumps only where steps stop at it (else where a step straddles the jump depends on
    the step sizes, which finite differences see and the detached controller does not)."""
    method, options = CASES[case]
    ts = torch.tensor([0.0, 0.2, 0.5], dtype=torch.float64)
    tight = {} if "fixed_dt" in options else {"rtol": 1e-10, "atol": 1e-12}
    jump = "tstops" in options

    def run(y0, theta):
        return solve(problem(theta, jump), y0, ts, method=method, **{**options, **tight}).ys

    y0 = torch.tensor([[[0.3, -0.7], [1.1, 0.2]]], dtype=torch.float64, requires_grad=True)
    theta = torch.tensor([0.8, 0.5, 0.3], dtype=torch.float64, requires_grad=True)
    # fast_mode checks vᵀJu for random u, v (one backward, a directional difference)
    # instead of every entry of J: a wrong entry of the fused backward still shows in vᵀJu.
    assert torch.autograd.gradcheck(run, (y0, theta), eps=1e-6, atol=1e-6, rtol=1e-4,
                                    fast_mode=True)


def test_fused_backward_agrees_when_a_sample_fails():
    """A sample that blows up is frozen and its later outputs are NaN; the others' gradients
    are autograd's, and finite."""
    theta = torch.tensor(1.0, dtype=torch.float64, requires_grad=True)
    y0 = torch.tensor([[0.1], [1.0], [0.3]], dtype=torch.float64)
    ts = torch.linspace(0.0, 2.0, 9, dtype=torch.float64)
    grads = []
    for fused in (True, False):
        sol = solve(lambda t, y: theta * y**2, y0, ts, fused=fused)
        assert sol.status[1] != Status.SUCCESS
        grads.append(torch.autograd.grad(sol.ys[[0, 2]].sum(), theta)[0])
    assert torch.isfinite(grads[0])
    torch.testing.assert_close(grads[0], grads[1], rtol=1e-10, atol=0)


def test_a_retained_graph_gives_the_same_gradients_twice():
    theta = torch.tensor([0.8, 0.5, 0.3], dtype=torch.float64, requires_grad=True)
    y0 = torch.randn(3, 2, 2, dtype=torch.float64)
    ts = torch.linspace(0.0, 1.0, 11, dtype=torch.float64)
    loss = solve(problem(theta), y0, ts, tstops=[SWITCH]).ys.square().sum()
    first = torch.autograd.grad(loss, theta, retain_graph=True)[0]
    second = torch.autograd.grad(loss, theta)[0]
    torch.testing.assert_close(first, second, rtol=0, atol=0)


def test_float32_gradients_agree_with_autograd_to_its_precision():
    """The training setting (float32, loose tolerances, the I controller)."""
    theta = torch.tensor([0.8, 0.5, 0.3], requires_grad=True)
    y0 = torch.randn(16, 2, 2, generator=torch.Generator().manual_seed(1))
    ts = torch.linspace(0.0, 2.5, 51, dtype=torch.float64)
    grads = []
    for fused in (True, False):
        sol = solve(problem(theta), y0, ts, rtol=1e-4, atol=1e-4, controller="i", fused=fused)
        grads.append(torch.autograd.grad(sol.ys.square().mean(), theta)[0])
    torch.testing.assert_close(grads[0], grads[1], rtol=1e-5, atol=1e-7)


def test_higher_derivatives_need_the_recorded_step():
    """The fused backward writes its buffers outside autograd: asked to record itself for a
    second derivative it raises, and `fused=False` gives one (y' = −θy², y(0) = 1:
    y(1) = 1 / (1 + θ), d²y/dθ² = 2 / (1 + θ)³)."""
    theta = torch.tensor(0.5, dtype=torch.float64, requires_grad=True)
    y0 = torch.ones(1, 1, dtype=torch.float64)
    sol = solve(lambda t, y: -theta * y**2, y0, [0.0, 1.0], rtol=1e-10, atol=1e-12)
    with pytest.raises(RuntimeError, match=r"first-order.*fused=False"):
        torch.autograd.grad(sol.ys[0, -1, 0], theta, create_graph=True)
    sol = solve(lambda t, y: -theta * y**2, y0, [0.0, 1.0], rtol=1e-10, atol=1e-12,
                fused=False)
    (first,) = torch.autograd.grad(sol.ys[0, -1, 0], theta, create_graph=True)
    (second,) = torch.autograd.grad(first, theta)
    assert second.item() == pytest.approx(2 / 1.5**3, rel=1e-6)


@pytest.mark.parametrize("options", [{}, {"fixed_dt": 0.1}])
def test_gradients_reach_y0_when_f_does_not_depend_on_the_state(options):
    """y' = u(t): y(t) = y0 + ∫u, so ∂y(t)/∂y0 = 1 although f records nothing."""
    y0 = torch.tensor([[0.5], [-1.0]], dtype=torch.float64, requires_grad=True)
    ts = torch.linspace(0.0, 1.0, 6, dtype=torch.float64)
    sol = solve(lambda t, y: torch.cos(t)[:, None], y0, ts, **options)
    (grad,) = torch.autograd.grad(sol.ys.sum(), y0)
    torch.testing.assert_close(grad, torch.full_like(y0, 6.0), rtol=0, atol=1e-12)
