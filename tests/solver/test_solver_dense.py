"""Dense output (`mpnode_cli/solver/dense.py`): its weights and sums against numpy's, to the
rounding of two summation orders, and a solve's outputs against a closed form."""

from __future__ import annotations

import numpy as np
import torch

from mpnode_cli.solver import dense, solve


def two_sums_apart(terms: int, magnitude):
    """How far two float64 sums of the same `terms` numbers may differ when they are added
    in different orders or vector widths: each is within γ_n·Σ|x_i| of the exact sum,
    γ_n = n·u/(1 − n·u) (Higham, *Accuracy and Stability of Numerical Algorithms*, 2nd ed.,
    §4.2), so the two within twice that. `magnitude` is Σ|x_i|."""
    u = np.finfo(np.float64).eps / 2
    return 2 * terms * u / (1 - terms * u) * magnitude


def test_weights_and_lanes_match_numpy():
    """b_i(θ) = Σ_k P_ik θ^k (`interpolant_weights`), and y + Σ_i b_i·h·k_i as recorded steps
    form it (`lanes`) and as fused steps write it (`write_lanes`), against numpy."""
    gen = torch.Generator().manual_seed(0)
    theta = torch.rand(16, 3, generator=gen, dtype=torch.float64)
    interp_t = torch.randn(7, 4, generator=gen, dtype=torch.float64)  # (s, K)
    coef = dense.interpolant_weights(theta, interp_t)
    assert coef.shape == (16, 3, 7)
    powers = theta.numpy()[..., None] ** np.arange(1, 5)  # (B, W, K)
    # K products (θ^k) and a sum of K terms each.
    apart = two_sums_apart(2 * 4, np.abs(powers) @ np.abs(interp_t.numpy()).T)
    assert (np.abs(coef.numpy() - powers @ interp_t.numpy().T) <= apart).all()

    hk = torch.randn(7, 16, 5, generator=gen, dtype=torch.float64)  # (s, B, F)
    y = torch.randn(16, 5, generator=gen, dtype=torch.float64)
    c, h, yn = coef.numpy(), hk.numpy(), y.numpy()
    want = yn[:, None] + np.einsum("bws,sbf->bwf", c, h)  # (B, W, F)
    apart = two_sums_apart(8, np.abs(yn)[:, None] + np.einsum("bws,sbf->bwf", np.abs(c),
                                                              np.abs(h)))
    assert (np.abs(dense.lanes(coef, hk, y).numpy() - want) <= apart).all()
    out = torch.zeros(16 * 3 + 1, 5, dtype=torch.float64)
    rows = torch.randperm(16 * 3, generator=gen)
    dense.write_lanes(out, rows, coef, hk, y)
    assert (np.abs(out[rows].numpy() - want.reshape(-1, 5)) <= apart.reshape(-1, 5)).all()
    assert not out[-1].any()  # the row no lane names is untouched


def test_a_linear_ode_matches_its_closed_form():
    """y' = λ·y + sin(ωt), scalar per sample, each sample at its own times:
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
