"""Compaction in the neural ODEs' rollouts (`SolverOptions.compact`): a rollout whose solve
goes on with its running trajectories only equals the rollout without compaction, states and
gradients; an ensemble keeps whole members, and a member equals the member alone."""

from __future__ import annotations

import importlib

import pytest
import torch

import mpnode_cli.models.ode  # noqa: F401  (binds `solve` before the module is patched)
from mpnode_cli.graphs.matrices import EdgeBatch
from mpnode_cli.models.ensemble import Ensemble
from mpnode_cli.models.registry import build_model
from mpnode_cli.solver.options import SolverOptions

solve_module = importlib.import_module("mpnode_cli.solver.solve")
adaptive = importlib.import_module("mpnode_cli.solver.adaptive")

TIGHT = {"rtol": 1e-7, "atol": 1e-7}


@pytest.fixture
def solves(monkeypatch):
    """The batch size of each adaptive solve run (one per restart), in a list; compaction
    may drop a single row (the batches here are small)."""
    sizes = []
    inner = solve_module.solve_adaptive

    def counting(problem, fun, shaped, y, *args, **kwargs):
        sizes.append(y.shape[0])
        return inner(problem, fun, shaped, y, *args, **kwargs)

    monkeypatch.setattr(solve_module, "solve_adaptive", counting)
    monkeypatch.setattr(adaptive, "COMPACT_MIN_DROP", 1)
    return sizes


def model(kind: str, options: dict, seed: int = 0):
    torch.manual_seed(seed)
    return build_model(kind, {"node_dim": 2, "control_dim": 1, "num_nodes": 5,
                              **options}).double()


def batch(b: int = 16, t: int = 6):
    """Trajectories of small and of large states, one after the other, so that their step
    counts differ."""
    torch.manual_seed(1)
    ts = torch.linspace(0, 1, t, dtype=torch.float64)
    adjacency = (torch.rand(b, 5, 5) < 0.4).double()
    scale = torch.where(torch.arange(b) % 2 == 0, 1e-2, 10.0).double()[:, None, None]
    x0 = torch.randn(b, 5, 2, dtype=torch.float64) * scale
    u = torch.randn(b, t, 5, 1, dtype=torch.float64)
    return x0, ts, adjacency, u


KINDS = [("mpnode", {"update": "mlp", "aggregate": "pna"}, False),
         ("mpnode", {"backend": "scatter"}, True),
         ("gnode", {"graph": "sys"}, False), ("node", {}, False)]


@pytest.mark.parametrize("kind, options, edges", KINDS)
def test_a_rollout_with_compaction_equals_the_rollout_without(kind, options, edges, solves):
    x0, ts, adjacency, u = batch()
    net = model(kind, options)
    net.fit_statistics(None, 0.1, adjacency)
    graph = EdgeBatch.from_adjacency(adjacency) if edges else adjacency
    params = list(net.parameters())
    weight = torch.randn(x0.shape[0], ts.numel(), 5, 2, dtype=torch.float64)
    outs, grads = [], []
    for compact in (True, False):
        out = net.rollout(x0, ts, graph, u, solver=SolverOptions(**TIGHT, compact=compact))
        outs.append(out)
        grads.append(torch.autograd.grad((out.states * weight).sum(), params,
                                         allow_unused=True))
        if compact:
            assert len(solves) >= 2 and solves[1] < solves[0]  # it compacted
    assert outs[0].status.tolist() == outs[1].status.tolist()
    torch.testing.assert_close(outs[0].states, outs[1].states, rtol=1e-10, atol=1e-12)
    for got, want in zip(*grads, strict=True):
        assert (got is None) == (want is None)
        if got is not None:
            torch.testing.assert_close(got, want, rtol=1e-10, atol=1e-12)


@pytest.mark.parametrize("kind, options, edges", KINDS)
def test_an_ensemble_compacts_whole_members_and_a_member_equals_it_alone(kind, options, edges,
                                                                         solves):
    x0, ts, adjacency, u = batch(8)
    graph = EdgeBatch.from_adjacency(adjacency) if edges else adjacency
    members = [model(kind, options, seed) for seed in range(3)]
    with torch.no_grad():  # members of different speeds: the first is done first
        for m, gain in zip(members, (0.3, 0.6, 1.0), strict=True):
            for p in m.parameters():
                p.mul_(gain)
    for m in members:
        m.fit_statistics(None, 0.1, adjacency)
    out = Ensemble(members).rollout(x0, ts, graph, u, solver=SolverOptions(**TIGHT))
    assert solves[0] == 24 and len(solves) >= 2
    assert all(n % 8 == 0 and n < 24 for n in solves[1:])  # whole members of 8 rows
    solver = SolverOptions(**TIGHT, compact=False)
    alone = [m.rollout(x0, ts, graph, u, solver=solver) for m in members]
    torch.testing.assert_close(out.members, torch.stack([a.states for a in alone]), rtol=1e-10,
                               atol=1e-12)
    assert out.member_status.tolist() == [a.status.tolist() for a in alone]
    # Gradients reach each member's own tensors as its rollout alone gives them; here the
    # member that ran longest, whose rows the compacted solve went on with.
    k = max(range(3), key=lambda i: alone[i].n_f_evals)
    g_ens = torch.autograd.grad(out.members[k].square().sum(), list(members[k].parameters()),
                                allow_unused=True)
    g_alone = torch.autograd.grad(alone[k].states.square().sum(),
                                  list(members[k].parameters()), allow_unused=True)
    for got, want in zip(g_ens, g_alone, strict=True):
        assert (got is None) == (want is None)
        if got is not None:
            torch.testing.assert_close(got, want, rtol=1e-8, atol=1e-10)
