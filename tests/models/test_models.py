"""MP-NODE model: equivariance, locality of messages, aggregation, losses, normalization."""

from __future__ import annotations

import pytest
import torch
import torch.nn.functional as F

from mpnode_cli.data.dataset import Normalizer
from mpnode_cli.models.ode import control_stops, zoh_controls
from mpnode_cli.models.registry import build_model
from mpnode_cli.solver import solve
from mpnode_cli.solver.options import SolverOptions
from mpnode_cli.training.losses import huber_loss, mse_loss

pytestmark = pytest.mark.usefixtures("float64_default")


def random_graph(batch: int, nodes: int, p: float, seed: int) -> torch.Tensor:
    gen = torch.Generator().manual_seed(seed)
    a = (torch.rand(batch, nodes, nodes, generator=gen) < p).double()
    return a * (1 - torch.eye(nodes))


def model(**kw):
    torch.manual_seed(0)
    cfg = {"node_dim": 3, "message_dim": 4, "hidden": 16} | kw
    return build_model("mpnode", cfg)


TS = torch.linspace(0.0, 1.0, 6, dtype=torch.float64)
TIGHT = SolverOptions(rtol=1e-9, atol=1e-9)


@pytest.mark.parametrize("aggregate", ["mean", "sum", "pna"])
def test_permutation_equivariance(aggregate):
    net = model(aggregate=aggregate)
    adj = random_graph(2, 6, 0.5, seed=1)
    net.fit_statistics(None, 0.1, adj)
    x0 = torch.randn(2, 6, 3)
    perm = torch.tensor([3, 0, 5, 1, 4, 2])
    out = net.rollout(x0, TS, adj, solver=TIGHT, return_messages=True)
    out_p = net.rollout(x0[:, perm], TS, adj[:, perm][:, :, perm], solver=TIGHT,
                        return_messages=True)
    torch.testing.assert_close(out_p.states, out.states[:, :, perm], rtol=1e-7, atol=1e-9)
    torch.testing.assert_close(out_p.messages, out.messages[:, :, perm], rtol=1e-7, atol=1e-9)


def two_components() -> torch.Tensor:
    """Nodes 0–1–2 (a path) and 3–4 (an edge): [1, 5, 5]."""
    a = torch.zeros(1, 5, 5)
    for i, j in [(0, 1), (1, 2), (3, 4)]:
        a[0, i, j] = a[0, j, i] = 1.0
    return a


@pytest.mark.parametrize("messages", [True, False])
def test_messages_reach_exactly_the_connected_component(messages):
    net = model(messages=messages)
    adj = two_components()
    x0 = torch.randn(1, 5, 3)
    moved = x0.clone()
    moved[0, 2] += 1.0  # change node 2 only
    a = net.rollout(x0, TS, adj, solver=SolverOptions(fixed_dt=0.05)).states
    b = net.rollout(moved, TS, adj, solver=SolverOptions(fixed_dt=0.05)).states
    changed = (a - b).abs().amax(dim=(0, 1, 3)) > 1e-9  # per node
    if messages:
        assert changed.tolist() == [True, True, True, False, False]
    else:
        assert changed.tolist() == [False, False, True, False, False]
    torch.testing.assert_close(a[0, :, 3:], b[0, :, 3:], rtol=0, atol=0)


def test_full_graph_mode_couples_every_node():
    net = model(graph="full")
    adj = two_components()
    x0 = torch.randn(1, 5, 3)
    moved = x0.clone()
    moved[0, 2] += 1.0
    a = net.rollout(x0, TS, adj, solver=SolverOptions(fixed_dt=0.05)).states
    b = net.rollout(moved, TS, adj, solver=SolverOptions(fixed_dt=0.05)).states
    assert bool(((a - b).abs().amax(dim=(0, 1, 3)) > 1e-9).all())


@pytest.mark.parametrize("aggregate", ["mean", "sum", "pna"])
def test_dense_and_scatter_models_give_the_same_rollout(aggregate):
    adj = random_graph(2, 6, 0.5, seed=3)
    x0 = torch.randn(2, 6, 3)
    nets = [model(aggregate=aggregate, backend=backend) for backend in ("dense", "scatter")]
    for net in nets:
        net.fit_statistics(x0, 0.1, adj)
    a = nets[0].rollout(x0, TS, adj, solver=SolverOptions(fixed_dt=0.1)).states
    b = nets[1].rollout(x0, TS, adj, solver=SolverOptions(fixed_dt=0.1)).states
    torch.testing.assert_close(a, b)


def test_zero_order_hold_controls_switch_at_sample_times():
    ts = torch.tensor([0.0, 0.5, 1.0])
    controls = torch.arange(2 * 3 * 1 * 1, dtype=torch.float64).reshape(2, 3, 1, 1)
    u = zoh_controls(controls, ts)
    t = torch.tensor([0.0, 0.4999, 0.5, 0.9999, 1.0])
    for tt in t:
        k = 0 if tt < 0.5 else 1
        torch.testing.assert_close(u(tt.repeat(2)), controls[:, k])


def test_controlled_model_integrates_a_held_input():
    """With a net that is exactly ẋ = u, the rollout is the integral of the held controls."""
    net = model(node_dim=1, control_dim=1, message_dim=1, hidden=2, layers=1)
    with torch.no_grad():
        for p in net.parameters():
            p.zero_()
        # hidden = tanh(0) = 0, so set the output bias path instead: ẋ = u via a skip weight.
        net.net[0].weight[0, 1] = 1e-3  # hidden_0 = tanh(1e-3 u) ≈ 1e-3 u
        net.net[2].weight[0, 0] = 1e3
    ts = torch.tensor([0.0, 0.5, 1.0])
    controls = torch.tensor([[[[0.2]], [[-0.4]], [[9.0]]]])  # [1, 3, 1, 1]
    out = net.rollout(torch.zeros(1, 1, 1), ts, torch.zeros(1, 1, 1), controls,
                      solver=SolverOptions(rtol=1e-10, atol=1e-12))
    want = torch.tensor([0.0, 0.1, -0.1])
    torch.testing.assert_close(out.states[0, :, 0, 0], want, rtol=1e-5, atol=1e-6)


def test_control_stops_are_the_samples_where_some_control_changes():
    ts = torch.arange(6, dtype=torch.float64) * 0.5
    controls = torch.ones(3, 6, 2, 2)  # [B, T, N, U]
    assert control_stops(controls, ts) is None  # constant: no stop at all
    assert control_stops(None, ts) is None
    controls[1, 3:, 1, 0] = 2.0  # one trajectory, node and component switches at ts[3]
    controls[2, 5] = -1.0  # the last sample's control is never held: no stop
    torch.testing.assert_close(control_stops(controls, ts), ts[3:4])
    controls[0, 1:] = 0.0
    torch.testing.assert_close(control_stops(controls, ts), ts[[1, 3]])


def held_input_net():
    """An MP-NODE whose vector field is exactly ẋ = 1e3·tanh(1e-3·u), ṁ = 0 (u ≠ 0 held)."""
    net = model(node_dim=1, control_dim=1, message_dim=1, hidden=2, layers=1)
    with torch.no_grad():
        for p in net.parameters():
            p.zero_()
        net.net[0].weight[0, 1] = 1e-3
        net.net[2].weight[0, 0] = 1e3
    return net


def test_constant_controls_integrate_like_a_solve_without_stops():
    """A constant control needs no stops: the rollout is the very solve without tstops
    (same steps, same states), and cheaper than stopping at every sample."""
    net = model(node_dim=3, control_dim=2)
    adj = random_graph(2, 5, 0.5, seed=9)
    x0 = torch.randn(2, 5, 3)
    ts = torch.linspace(0.0, 2.0, 21, dtype=torch.float64)
    controls = torch.randn(2, 1, 5, 2).expand(2, 21, 5, 2)  # [B, T, N, U], held throughout
    solver = SolverOptions(rtol=1e-6, atol=1e-6)
    out = net.rollout(x0, ts, adj, controls, solver=solver)
    f = net.vector_field(adj, zoh_controls(controls, ts))
    z0 = torch.cat([x0, x0.new_zeros(2, 5, net.message_dim)], dim=-1)
    plain = solve(f, z0, ts, **solver.solve_kwargs())
    assert out.n_f_evals == int(plain.stats["n_f_evals"].max())
    torch.testing.assert_close(out.states, plain.ys[..., :3], rtol=0, atol=0)
    every_sample = solve(f, z0, ts, **solver.solve_kwargs(), tstops=ts[1:-1])
    assert out.n_f_evals < int(every_sample.stats["n_f_evals"].max())


def test_a_switching_control_gets_a_stop_there_and_the_piecewise_solution():
    net = held_input_net()
    ts = torch.linspace(0.0, 1.0, 6, dtype=torch.float64)
    u = torch.tensor([0.7, 0.7, 0.7, -1.3, -1.3, -1.3])  # switches at ts[3]
    controls = u.reshape(1, 6, 1, 1)
    assert control_stops(controls, ts).tolist() == [ts[3].item()]
    out = net.rollout(torch.zeros(1, 1, 1), ts, torch.zeros(1, 1, 1), controls,
                      solver=SolverOptions(rtol=1e-4, atol=1e-4))
    rate = 1e3 * torch.tanh(1e-3 * u[:-1])  # ẋ on each [ts[k], ts[k+1])
    want = torch.cat([torch.zeros(1), torch.cumsum(rate * 0.2, 0)])
    # RK is exact on a piecewise-constant field whose pieces meet at step ends.
    torch.testing.assert_close(out.states[0, :, 0, 0], want, rtol=0, atol=1e-12)


@pytest.mark.parametrize("kind", ["mpnode", "gnode", "node"])
def test_every_ode_model_stops_only_where_controls_change(kind, monkeypatch):
    from mpnode_cli.models import ode as module  # the one rollout every ODE model runs

    seen = []

    def spy(*args, tstops=None, **kw):
        seen.append(tstops)
        return solve(*args, tstops=tstops, **kw)

    monkeypatch.setattr(module, "solve", spy)
    torch.manual_seed(0)
    net = build_model(kind, {"node_dim": 2, "control_dim": 1, "num_nodes": 4})
    ts = torch.linspace(0.0, 1.0, 6, dtype=torch.float64)
    controls = torch.ones(2, 6, 4, 1)
    adj = random_graph(2, 4, 0.6, seed=2)
    net.rollout(torch.randn(2, 4, 2), ts, adj, controls)
    controls[0, 2:] = 3.0
    net.rollout(torch.randn(2, 4, 2), ts, adj, controls)
    assert seen[0] is None
    assert seen[1].tolist() == [ts[2].item()]


def test_gradients_reach_every_parameter():
    net = model()
    adj = random_graph(2, 4, 0.7, seed=4)
    out = net.rollout(torch.randn(2, 4, 3), TS, adj)
    huber_loss(out.states, torch.zeros_like(out.states)).backward()
    for name, p in net.named_parameters():
        assert p.grad is not None and torch.isfinite(p.grad).all(), name
        assert p.grad.abs().sum() > 0, name


def test_wrong_feature_size_is_a_clear_error():
    with pytest.raises(ValueError, match="expects 3"):
        model().rollout(torch.randn(1, 4, 2), TS, torch.ones(1, 4, 4))
    with pytest.raises(ValueError, match="unknown model"):
        build_model("nope", {})


def test_losses_against_torch_reference():
    gen = torch.Generator().manual_seed(5)
    pred, target = torch.randn(4, 6, 3, 2, generator=gen) * 2, torch.randn(4, 6, 3, 2,
                                                                           generator=gen)
    ref = F.huber_loss(pred[:, 1:], target[:, 1:], reduction="none", delta=1.0)
    assert huber_loss(pred, target).item() == pytest.approx(ref.sum(dim=(1, 3)).mean().item())
    assert mse_loss(pred, target).item() == pytest.approx(
        F.mse_loss(pred[:, 1:], target[:, 1:]).item())
    # t0 is excluded: changing it changes nothing.
    pred2 = pred.clone()
    pred2[:, 0] += 10
    assert huber_loss(pred2, target) == huber_loss(pred, target)


def test_normalizer_standardises_and_round_trips():
    gen = torch.Generator().manual_seed(6)
    states = torch.randn(10, 5, 4, 2, generator=gen) * torch.tensor([3.0, 0.1]) + 7
    states[..., 1] = 2.5  # a constant feature is centred, not divided by zero
    norm = Normalizer.fit(states)
    z = norm.norm_x(states)
    torch.testing.assert_close(z[..., 0].mean(), torch.tensor(0.0), atol=1e-6, rtol=0)
    torch.testing.assert_close(z[..., 0].std(correction=0), torch.tensor(1.0), atol=1e-5,
                               rtol=0)
    assert torch.equal(z[..., 1], torch.zeros_like(z[..., 1]))
    back = Normalizer.from_dict(norm.to_dict())
    torch.testing.assert_close(back.denorm_x(z), states, rtol=1e-5, atol=1e-5)


def test_normalizer_of_several_datasets_pools_their_values():
    """Datasets of 3 and 5 nodes: the z-score of every value of both, as if one array."""
    gen = torch.Generator().manual_seed(7)
    a = torch.randn(4, 6, 3, 2, generator=gen) * 2 + 1
    b = torch.randn(2, 9, 5, 2, generator=gen) - 3
    norm = Normalizer.fit([a, b])
    values = torch.cat([a.reshape(-1, 2), b.reshape(-1, 2)]).double()
    torch.testing.assert_close(norm.x_mean, values.mean(0).float())
    torch.testing.assert_close(norm.x_std, values.std(0, correction=0).float())
    one, listed = Normalizer.fit(a), Normalizer.fit([a])  # a list of one: bit for bit
    assert all(torch.equal(getattr(one, f), getattr(listed, f))
               for f in ("x_mean", "x_std", "u_mean", "u_std"))


def test_step_statistics_of_several_datasets_pool_their_steps():
    """L2S's Δ moments over datasets of 3 and 5 nodes: those of all their steps at once."""
    gen = torch.Generator().manual_seed(8)
    a, b = torch.randn(3, 5, 3, 2, generator=gen), torch.randn(2, 4, 5, 2, generator=gen)
    net = build_model("l2s", {"node_dim": 2})
    net.fit_statistics([a, b], 0.1)
    steps = torch.cat([(a[:, 1:] - a[:, :-1]).reshape(-1, 2),
                       (b[:, 1:] - b[:, :-1]).reshape(-1, 2)])
    close = {"rtol": 1e-6, "atol": 1e-7}  # the buffers hold float32-rounded moments
    torch.testing.assert_close(net.delta_mean, steps.mean(0), **close)
    torch.testing.assert_close(net.delta_std, steps.std(0, correction=0), **close)


@pytest.mark.parametrize(("kind", "aggregate"), [
    ("mpnode", "mean"), ("mpnode", "sum"), ("mpnode", "pna"),
    ("gnode", "sum"), ("gnode", "pna"), ("l2s", None)])
def test_models_run_from_edge_lists_as_from_matrices(kind, aggregate):
    """Every model that aggregates, given its graphs as an `EdgeBatch` (what training passes
    for large graphs): the same δ, rollout and training loss as from `[B, N, N]` matrices."""
    from mpnode_cli.graphs.matrices import EdgeBatch

    adj = random_graph(3, 7, 0.4, seed=8)
    edges = EdgeBatch.from_adjacency(adj)
    torch.manual_seed(0)
    cfg = {"node_dim": 3} | ({"aggregate": aggregate} if aggregate else {})
    nets = [build_model(kind, cfg) for _ in range(2)]
    nets[1].load_state_dict(nets[0].state_dict())
    x = torch.randn(3, 6, 7, 3)
    nets[0].fit_statistics(x, 0.2, adj)
    nets[1].fit_statistics(x, 0.2, edges)
    assert nets[0].state_dict().keys() == nets[1].state_dict().keys()
    for key, value in nets[0].state_dict().items():
        torch.testing.assert_close(nets[1].state_dict()[key], value, msg=key)
    ts = torch.arange(6, dtype=torch.float64) * 0.2
    solver = SolverOptions(fixed_dt=0.1)
    by_matrix = nets[0].rollout_from_data(x, ts, adj, solver=solver).states
    by_edges = nets[1].rollout_from_data(x, ts, edges, solver=solver).states
    torch.testing.assert_close(by_edges, by_matrix)
    torch.manual_seed(1)  # L2S draws its input noise
    loss_m = nets[0].training_loss(x, ts, adj, None, mse_loss, solver=solver).loss
    torch.manual_seed(1)
    loss_e = nets[1].training_loss(x, ts, edges, None, mse_loss, solver=solver).loss
    torch.testing.assert_close(loss_e, loss_m)


def test_l2s_processor_is_its_definition_edge_by_edge():
    """L2S's Δ̂ against its definition written out node by node: every step, each node's
    edges e_ij = f_e([h_i, h_j]) over its in-neighbours j (an edge of multiplicity 2 twice),
    h_i ← h_i + f_n([h_i, Σ_j e_ij]); the model applies f_e's first layer per node."""
    adj = random_graph(2, 6, 0.5, seed=3)
    adj[1, 2, 4] = 2.0  # a double edge 4 → 2
    torch.manual_seed(0)
    net = build_model("l2s", {"node_dim": 2, "latent": 8, "hidden": 8, "steps": 3})
    x = torch.randn(2, 1, 6, 2)
    got = net.delta(x, net.edge_index(adj), None)
    for b in range(2):
        h = net.encoder(x[b, 0])
        for edge_fn, node_fn in zip(net.edge_fns, net.node_fns, strict=True):
            summed = torch.zeros_like(h)
            for i in range(6):
                for j in range(6):
                    for _ in range(int(adj[b, i, j])):
                        summed[i] += edge_fn(torch.cat([h[i], h[j]]))
            h = h + node_fn(torch.cat([h, summed], dim=-1))
        torch.testing.assert_close(got[b], net.decoder(h), rtol=1e-10, atol=1e-12)


@pytest.mark.parametrize("unroll", [1, 2])
def test_l2s_windows_train_on_k_random_steps_of_each_trajectory(unroll):
    """With `windows` k, L2S's training loss is the mean of the losses of k distinct windows
    of each trajectory, each window's as if it were a trajectory of its own: one of the
    subsets' means, another from draw to draw; k at least the windows is all of them."""
    from itertools import combinations

    torch.manual_seed(0)
    net = build_model("l2s", {"node_dim": 2, "latent": 8, "hidden": 8, "steps": 2})
    adj = random_graph(2, 4, 0.6, seed=1)
    x = torch.randn(2, 4 + unroll, 4, 2)  # 4 windows per trajectory

    @torch.no_grad()
    def loss(states, graph, k=0):
        if unroll == 1:
            return float(net.one_step_loss(states, graph, noise_std=0, windows=k))
        return float(net.unrolled_loss(states, graph, steps=unroll, noise_std=0, windows=k))

    each = [[loss(x[b:b + 1, s:s + 1 + unroll], adj[b:b + 1]) for s in range(4)]
            for b in range(2)]
    means = [(sum(each[0][i] for i in p) + sum(each[1][j] for j in q)) / 4
             for p in combinations(range(4), 2) for q in combinations(range(4), 2)]
    seen = set()
    for _ in range(20):
        got = loss(x, adj, k=2)
        hits = [i for i, m in enumerate(means) if abs(m - got) <= 1e-12 * abs(m)]
        assert len(hits) == 1, got
        seen.add(hits[0])
    assert len(seen) > 5
    everything = sum(sum(e) for e in each) / 8
    assert loss(x, adj, k=4) == pytest.approx(everything, rel=1e-12)
    assert loss(x, adj, k=9) == loss(x, adj)
