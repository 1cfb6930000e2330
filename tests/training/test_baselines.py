"""Baseline models: L2S, the authors' GNN-ODE and the monolithic NODE."""

from __future__ import annotations

import pytest
import torch

from mpnode_cli.models.registry import build_model
from mpnode_cli.solver.options import SolverOptions

pytestmark = pytest.mark.usefixtures("float64_default")


def random_graph(batch: int, nodes: int, seed: int) -> torch.Tensor:
    gen = torch.Generator().manual_seed(seed)
    a = (torch.rand(batch, nodes, nodes, generator=gen) < 0.5).double()
    return a * (1 - torch.eye(nodes))


def built(kind: str, **kw):
    torch.manual_seed(0)
    return build_model(kind, {"node_dim": 2} | kw)


TS = torch.linspace(0.0, 0.5, 6, dtype=torch.float64)
TIGHT = SolverOptions(rtol=1e-9, atol=1e-9)


@pytest.mark.parametrize("kind, options", [
    ("l2s", {"latent": 16, "hidden": 16, "steps": 3}),
    ("gnode", {"hidden": 8}),
    ("gnode", {"hidden": 8, "aggregate": "pna"}),
    ("mpnode", {"hidden": 8}),
])
def test_graph_models_are_permutation_equivariant(kind, options):
    net = built(kind, **options)
    adj = random_graph(2, 5, seed=1)
    if kind != "l2s":
        net.fit_statistics(None, 0.1, adj)
    x0 = torch.randn(2, 5, 2)
    perm = torch.tensor([4, 2, 0, 3, 1])
    a = net.rollout(x0, TS, adj, solver=TIGHT).states
    b = net.rollout(x0[:, perm], TS, adj[:, perm][:, :, perm], solver=TIGHT).states
    torch.testing.assert_close(b, a[:, :, perm], rtol=1e-7, atol=1e-9)


def test_l2s_rollout_applies_the_predicted_differences():
    net = built("l2s", latent=8, hidden=8, steps=2)
    adj = random_graph(1, 4, seed=2)
    x0 = torch.randn(1, 4, 2)
    out = net.rollout(x0, TS, adj).states
    edges = net.edge_index(adj)
    step1 = x0 + net.delta(x0.unsqueeze(1), edges, None) * net.delta_std + net.delta_mean
    torch.testing.assert_close(out[:, 1], step1)
    assert out.shape == (1, 6, 4, 2)


def test_l2s_statistics_and_one_step_loss():
    net = built("l2s", latent=8, hidden=8, steps=2, history=2)
    states = torch.randn(3, 7, 4, 2).cumsum(dim=1) * 0.1
    net.fit_statistics(states, dt=0.1)
    diff = states[:, 1:] - states[:, :-1]
    torch.testing.assert_close(net.delta_mean, diff.reshape(-1, 2).mean(0))
    loss = net.one_step_loss(states, random_graph(3, 4, seed=3), noise_std=0.0)
    assert loss.ndim == 0 and torch.isfinite(loss)
    loss.backward()
    assert all(p.grad is not None for p in net.parameters())
    with pytest.raises(ValueError, match="first 2 states"):
        net.rollout(states[:, 0], torch.arange(7) * 0.1, random_graph(3, 4, seed=3))
    out = net.rollout(states[:, 0], torch.arange(7) * 0.1, random_graph(3, 4, seed=3),
                      history=states[:, :2])
    torch.testing.assert_close(out.states[:, :2], states[:, :2])
    with pytest.raises(ValueError, match="training dt"):
        net.rollout(states[:, 0], torch.arange(7) * 0.2, random_graph(3, 4, seed=3),
                    history=states[:, :2])


def test_l2s_unrolled_loss_is_the_error_of_its_own_rollouts():
    """Without noise, `unrolled_loss` of k steps is the mean, over every start and the k
    steps, of the squared error of `rollout` from that start (a separate code path), over
    Δ's std; one step of it is `one_step_loss`. With controls and a history of 2."""
    net = build_model("l2s", {"node_dim": 2, "control_dim": 1, "latent": 8, "hidden": 8,
                              "steps": 2, "history": 2})
    states = torch.randn(2, 8, 3, 2).cumsum(dim=1) * 0.3
    controls = torch.randn(2, 8, 3, 1)
    adj = random_graph(2, 3, seed=5)
    net.fit_statistics(states, dt=0.1)
    ts = torch.arange(8, dtype=torch.float64) * 0.1
    k, c = 3, 2
    errors = []
    for start in range(8 - c - k + 1):
        span = slice(start, start + c + k)
        out = net.rollout(states[:, start + c - 1], ts[span], adj, controls[:, span],
                          history=states[:, start:start + c]).states
        errors.append(((out[:, c:] - states[:, start + c:start + c + k]) / net.delta_std)
                      .square().mean())
    expected = torch.stack(errors).mean()
    loss = net.unrolled_loss(states, adj, controls, steps=k, noise_std=0.0)
    torch.testing.assert_close(loss, expected)
    torch.testing.assert_close(net.unrolled_loss(states, adj, controls, steps=1, noise_std=0.0),
                               net.one_step_loss(states, adj, controls, noise_std=0.0))
    with pytest.raises(ValueError, match="needs more than 7 samples"):
        net.unrolled_loss(states[:, :7], adj, controls[:, :7], steps=6, noise_std=0.0)


def test_monolithic_node_refuses_another_node_count():
    net = built("node", num_nodes=3)
    out = net.rollout(torch.randn(2, 3, 2), TS, torch.ones(2, 3, 3))
    assert out.states.shape == (2, 6, 3, 2)
    assert not net.transferable
    with pytest.raises(ValueError, match="built for 3 nodes"):
        net.rollout(torch.randn(2, 5, 2), TS, torch.ones(2, 5, 5))


def test_gnode_matches_its_equations():
    """One evaluation of the vector field against the formulas written out."""
    net = built("gnode", hidden=4)
    adj = random_graph(1, 3, seed=4)
    x = torch.randn(1, 3, 2)
    f = net.vector_field(adj)
    h0 = torch.tanh(net.lift(x))
    msg = torch.tanh(net.message(h0))
    summed = torch.einsum("bij,bjh->bih", adj, msg)
    h = torch.tanh(net.update(summed)) + h0
    torch.testing.assert_close(f(torch.zeros(1), x), net.decode(h + h0))
