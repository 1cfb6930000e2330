"""Dynamical systems: right-hand sides against numpy loops written from the equations,
trajectories against closed forms and scipy, samplers, graphs and the registry."""

from __future__ import annotations

import math
import subprocess
import sys

import numpy as np
import pytest
import torch
from scipy.integrate import solve_ivp

from mpnode_cli.graphs.topologies import make_graph
from mpnode_cli.solver import solve
from mpnode_cli.systems import SYSTEMS, System, get_system
from mpnode_cli.systems.neighbour_sum import NeighbourSum

RNG_SEED = 20221029


def _random_graphs(k: int, n: int, rng: np.random.Generator) -> np.ndarray:
    """K random undirected graphs, uint8 [K, N, N], symmetric with zero diagonal."""
    upper = np.triu(rng.random((k, n, n)) < 0.5, 1)
    return (upper | upper.transpose(0, 2, 1)).astype(np.uint8)


def _torch_inputs(system: System, graphs: np.ndarray, rng: np.random.Generator):
    """Per-trajectory adjacency [K, N, N] and stacked graph_params, as the generator builds them."""
    params = [system.graph_params(a, rng) for a in graphs]
    stacked = {key: torch.from_numpy(np.stack([p[key] for p in params])) for key in params[0]}
    return torch.from_numpy(graphs.astype(np.float64)), stacked, params


def _eval_rhs(system: System, graphs: np.ndarray, y: np.ndarray, rng: np.random.Generator):
    adjacency, stacked, params = _torch_inputs(system, graphs, rng)
    f = system.rhs(adjacency, stacked)
    t = torch.zeros(len(graphs), dtype=torch.float64)
    return f(t, torch.from_numpy(y)).numpy(), params


# ----- numpy references, one node at a time, written from each system's equation -----------


def _pendulum_ref(a, y, p):
    """θ̈ from the linear oscillator in y = l sin θ: m ÿ_i = −(m g/l) y_i + k Σ_j A_ij (y_j − y_i),
    and ÿ = l cos θ θ̈ − l sin θ θ̇²."""
    m, length, k, g = p["m"], p["l"], p["k"], p["g"]
    n = len(a)
    out = np.zeros_like(y)
    for i in range(n):
        th, th_dot = y[i]
        yi = length * math.sin(th)
        spring = sum(a[i, j] * (length * math.sin(y[j, 0]) - yi) for j in range(n))
        y_ddot = (-(m * g / length) * yi + k * spring) / m
        out[i] = th_dot, (y_ddot + length * math.sin(th) * th_dot**2) / (length * math.cos(th))
    return out


def _lorenz_ref(y, h, sigma, rho, beta):
    n = len(y)
    flat = y.reshape(-1)
    out = np.zeros(3 * n)
    for i in range(n):
        x_, y_, z_ = y[i]
        out[3 * i : 3 * i + 3] = sigma * (y_ - x_), x_ * (rho - z_) - y_, x_ * y_ - beta * z_
    for r in range(3 * n):
        out[r] += sum(h[r, c] * flat[c] for c in range(3 * n))
    return out.reshape(n, 3)


def _gene_ref(a, x, b, f, h):
    n = len(a)
    out = np.zeros_like(x)
    for i in range(n):
        out[i, 0] = -b * x[i, 0] ** f
        for j in range(n):
            out[i, 0] += a[i, j] * x[j, 0] ** h / (1 + x[j, 0] ** h)
    return out


def _kuramoto_ref(a, theta, omega, coupling):
    n = len(a)
    out = np.zeros_like(theta)
    for i in range(n):
        for c in range(3):
            out[i, c] = omega[c] + coupling * sum(
                a[i, j] * math.sin(theta[j, c] - theta[i, c]) for j in range(n)
            )
    return out


# ----- right-hand sides ----------------------------------------------------------------------


def test_pendulum_rhs_matches_reference():
    rng = np.random.default_rng(RNG_SEED)
    params = {"m": 1.3, "l": 1.1, "k": 2.5, "g": 9.7}
    system = get_system("pendulum", **params)
    graphs = _random_graphs(3, 5, rng)
    y = np.stack([rng.uniform(-1.2, 1.2, (3, 5)), rng.uniform(-2, 2, (3, 5))], axis=-1)
    got, _ = _eval_rhs(system, graphs, y, rng)
    for b in range(3):
        np.testing.assert_allclose(got[b], _pendulum_ref(graphs[b], y[b], params), rtol=1e-12)


def test_pendulum_rhs_is_the_authors_two_node_formula():
    # MPNODE.jl src/systems/pendulum.jl, transcribed (x = [θ1, θ̇1, θ2, θ̇2]).
    m, l, k, g = 1.0, 1.5, 2.0, 9.81  # noqa: E741 (the authors' names)
    rng = np.random.default_rng(RNG_SEED)
    x = rng.uniform(-1, 1, size=(6, 4))
    th1 = (np.sin(x[:, 0]) * (m * (l * x[:, 1] ** 2 - g) - k * l) + k * l * np.sin(x[:, 2])) / (
        m * l * np.cos(x[:, 0])
    )
    th2 = (np.sin(x[:, 2]) * (m * (l * x[:, 3] ** 2 - g) - k * l) + k * l * np.sin(x[:, 0])) / (
        m * l * np.cos(x[:, 2])
    )
    graphs = np.repeat(make_graph("chain", 2, seed=0)[None], 6, axis=0)
    got, _ = _eval_rhs(get_system("pendulum"), graphs, x.reshape(6, 2, 2), rng)
    np.testing.assert_allclose(got[:, :, 1], np.stack([th1, th2], axis=1), rtol=1e-12)
    np.testing.assert_array_equal(got[:, :, 0], x.reshape(6, 2, 2)[:, :, 1])


@pytest.mark.parametrize("coupling", [0.01, 1.0])
def test_lorenz_rhs_matches_reference(coupling):
    rng = np.random.default_rng(RNG_SEED)
    system = get_system("lorenz", coupling=coupling, sigma=9.0, rho=27.0, beta=2.5)
    graphs = np.stack([make_graph("complete", 4, seed=0)] * 2 + [_random_graphs(1, 4, rng)[0]])
    y = rng.uniform(-15, 15, size=(3, 4, 3))
    got, params = _eval_rhs(system, graphs, y, rng)
    for b in range(3):
        ref = _lorenz_ref(y[b], params[b]["coupling"], 9.0, 27.0, 2.5)
        np.testing.assert_allclose(got[b], ref, rtol=1e-12, atol=1e-12)


def test_gene_rhs_matches_reference():
    rng = np.random.default_rng(RNG_SEED)
    system = get_system("gene", b=1.5, f=1.0, h=2.0)
    graphs = _random_graphs(3, 9, rng)
    x = rng.uniform(0, 50, size=(3, 9, 1))
    got, _ = _eval_rhs(system, graphs, x, rng)
    for b in range(3):
        np.testing.assert_allclose(got[b], _gene_ref(graphs[b], x[b], 1.5, 1.0, 2.0), rtol=1e-12)


def test_kuramoto_rhs_matches_reference():
    rng = np.random.default_rng(RNG_SEED)
    system = get_system("kuramoto", K=0.7)
    graphs = _random_graphs(3, 6, rng)
    theta = rng.uniform(-4, 4, size=(3, 6, 3))
    got, params = _eval_rhs(system, graphs, theta, rng)
    for b in range(3):
        ref = _kuramoto_ref(graphs[b], theta[b], params[b]["omega"], 0.7)
        np.testing.assert_allclose(got[b], ref, rtol=1e-12, atol=1e-12)


# Graphs in blocks, as the generator passes several graphs: trajectory k is on graph BLOCKS[k]
# (a graph may come back after others, which makes a new block).
BLOCKS = [0, 0, 0, 1, 1, 2, 2, 2, 2, 0, 0, 1]
EQUAL_BLOCKS = [0, 0, 0, 0, 1, 1, 1, 1, 2, 2, 2, 2]  # the generator's usual case


@pytest.mark.parametrize("d", [1, 3])
@pytest.mark.parametrize(
    ("order", "plan"),
    [
        (BLOCKS, "runs"),  # blocks of unequal length: one GEMM each
        (EQUAL_BLOCKS, "stacked"),  # equal blocks: one batched GEMM
        ([0] * 12, "stacked"),  # one graph in K copies
        ([0, 1, 2, 3, 4, 5, 5, 6, 7, 8, 9, 10], None),  # nearly a graph each: per trajectory
    ],
)
def test_neighbour_sum_in_blocks_equals_the_per_trajectory_product(order, plan, d):
    rng = np.random.default_rng(RNG_SEED)
    mats = torch.from_numpy(rng.standard_normal((max(order) + 1, 7, 7)))  # weighted, like H
    adjacency = mats[order]  # [12, 7, 7]
    x = torch.from_numpy(rng.standard_normal((12, 7, d)))
    product = NeighbourSum(adjacency)
    assert plan == ("stacked" if product.stacked is not None
                    else "runs" if product.runs is not None else None)  # fmt: skip
    torch.testing.assert_close(product(x), adjacency @ x, rtol=0, atol=1e-12)
    torch.testing.assert_close(NeighbourSum(mats[:1])(x), mats[0] @ x, rtol=0, atol=1e-12)


@pytest.mark.parametrize("order", [BLOCKS, EQUAL_BLOCKS], ids=["blocks", "equal_blocks"])
@pytest.mark.parametrize("name", ["pendulum", "lorenz", "gene", "kuramoto"])
def test_rhs_on_graphs_in_blocks_equals_each_trajectory_alone(name, order):
    rng = np.random.default_rng(RNG_SEED)
    system = get_system(name)
    graphs = _random_graphs(3, 6, rng)
    per_graph = [system.graph_params(a, rng) for a in graphs]
    adjacency = torch.from_numpy(graphs[order].astype(np.float64))  # [12, N, N]
    params = {key: torch.from_numpy(np.stack([per_graph[g][key] for g in order]))
              for key in per_graph[0]}  # fmt: skip
    y = torch.from_numpy(np.concatenate([system.sample_initial(graphs[g], 1, rng)
                                         for g in order]))  # fmt: skip
    t = torch.zeros(len(order), dtype=torch.float64)
    got = system.rhs(adjacency, params)(t, y)
    for k in range(len(order)):
        one = {key: value[k : k + 1] for key, value in params.items()}
        alone = system.rhs(adjacency[k : k + 1], one)(t[k : k + 1], y[k : k + 1])
        torch.testing.assert_close(got[k], alone[0], rtol=0, atol=1e-12)


# ----- per-graph parameters, samplers, rejection -----------------------------------------------


def test_lorenz_coupling_matrix():
    rng = np.random.default_rng(RNG_SEED)
    h = get_system("lorenz", coupling=0.5).graph_params(make_graph("complete", 4, 0), rng)
    h = h["coupling"]
    assert h.shape == (12, 12)
    assert math.isclose(np.linalg.norm(h), 0.5, rel_tol=1e-12)
    blocks = h.reshape(4, 3, 4, 3)  # [receiver, component, sender, component]
    for i in range(4):
        assert not blocks[i, :, i, :].any()
    off_diagonal = ~np.kron(np.eye(4, dtype=bool), np.ones((3, 3), dtype=bool))
    assert (h[off_diagonal] > 0).all()
    # Departure from the authors: blocks without an edge are zero (here a chain 0-1-2-3).
    h_chain = get_system("lorenz").graph_params(make_graph("chain", 4, 0), rng)["coupling"]
    assert not h_chain.reshape(4, 3, 4, 3)[0, :, 2, :].any()
    assert math.isclose(np.linalg.norm(h_chain), 0.01, rel_tol=1e-12)


def test_lorenz_single_node_is_uncoupled():
    rng = np.random.default_rng(RNG_SEED)
    h = get_system("lorenz").graph_params(np.zeros((1, 1), np.uint8), rng)["coupling"]
    np.testing.assert_array_equal(h, np.zeros((3, 3)))


def test_kuramoto_omega_per_graph():
    rng = np.random.default_rng(RNG_SEED)
    params = get_system("kuramoto").graph_params(make_graph("ba", 10, 0, m=5), rng)
    assert set(params) == {"omega"}
    assert params["omega"].shape == (3,)


def test_kuramoto_omega_seed_draws_other_frequencies_and_its_default_does_not():
    """By default ω comes from the graph's own generator, as it always has (BA and ER
    datasets of one graph seed share it); `omega_seed` draws other frequencies."""
    graph = make_graph("ba", 10, 0, m=5)

    def omega(**options):
        return get_system("kuramoto", **options).graph_params(
            graph, np.random.default_rng([0, 0]))["omega"]

    np.testing.assert_array_equal(omega(), np.random.default_rng([0, 0]).standard_normal(3))
    np.testing.assert_array_equal(omega(omega_seed=0), omega())
    assert not np.allclose(omega(omega_seed=1), omega())
    assert not np.allclose(omega(omega_seed=1), omega(omega_seed=2))
    np.testing.assert_array_equal(omega(omega_seed="1"), omega(omega_seed=1))  # -p gives text
    with pytest.raises(ValueError, match="omega_seed must be a whole number"):
        get_system("kuramoto", omega_seed=1.5)
    with pytest.raises(ValueError, match="omega_seed must be a finite number >= 0"):
        get_system("kuramoto", omega_seed=-1)


@pytest.mark.parametrize(
    ("name", "options", "low", "high"),
    [
        ("pendulum", {}, [-math.pi / 4, -0.5], [math.pi / 4, 0.5]),
        ("pendulum", {"ic_range": "paper"}, [-math.pi / 2, -1.0], [math.pi / 2, 1.0]),
        ("lorenz", {}, [-1.0] * 3, [1.0] * 3),
        ("gene", {}, [0.0], [50.0]),
        ("kuramoto", {}, [-1.0] * 3, [1.0] * 3),
    ],
)
def test_sample_initial_shapes_and_ranges(name, options, low, high):
    system = get_system(name, **options)
    n = 16
    states = system.sample_initial(np.zeros((n, n), np.uint8), 400, np.random.default_rng(1))
    assert states.shape == (400, n, system.node_dim)
    assert states.dtype == np.float64
    per_dim = states.reshape(-1, system.node_dim)
    assert (per_dim >= low).all() and (per_dim <= high).all()
    # The draws fill the box: each end is approached to within 2% of its width.
    width = np.subtract(high, low)
    assert (per_dim.min(axis=0) < np.add(low, 0.02 * width)).all()
    assert (per_dim.max(axis=0) > np.subtract(high, 0.02 * width)).all()


def test_gene_hotspot_initial_states():
    system = get_system("gene", init="hotspot")
    states = system.sample_initial(np.zeros((64, 64), np.uint8), 50, np.random.default_rng(3))
    assert states.shape == (50, 64, 1)
    hot = states[states > 0]
    assert ((hot >= 30) & (hot <= 50)).all()
    for state in states:
        values = np.unique(state[state > 0])
        assert 1 <= len(values) <= 3  # one value per rectangle, overlaps may hide some
        assert 0 < (state > 0).sum() < 64
    with pytest.raises(ValueError, match="square"):
        system.sample_initial(np.zeros((10, 10), np.uint8), 1, np.random.default_rng(0))


def test_pendulum_reject():
    system = get_system("pendulum")
    t = np.linspace(0, 1, 11)
    safe = np.zeros((11, 2, 2))
    safe[:, :, 0] = 0.5 * np.sin(t)[:, None]
    close = safe.copy()
    close[7, 1, 0] = math.pi / 2 - 5e-3  # |cos θ| ≈ 5e-3 at one sample
    blown_up = safe.copy()
    blown_up[3:, 0, 0] = np.nan
    assert system.reject(np.stack([safe, close, blown_up])).tolist() == [False, True, True]


@pytest.mark.parametrize("name", ["lorenz", "gene", "kuramoto"])
def test_other_systems_reject_nothing(name):
    states = np.random.default_rng(0).normal(size=(4, 5, 3, 1))
    assert not get_system(name).reject(states).any()


# ----- graphs per system, registry ----------------------------------------------------------------


@pytest.mark.parametrize(
    ("name", "topology", "n", "edge_count"),
    [
        ("pendulum", "chain", 2, 1),
        ("pendulum", "chain", 5, 4),
        ("lorenz", "complete", 10, 45),
        ("gene", "ba", 16, 8 * 8),  # m (n − m) with m = n/2
        ("gene", "ws", 16, 16 * 8 // 2),  # n k / 2 with k = n/2
        ("gene", "ba", 64, 32 * 32),
        ("kuramoto", "ba", 10, 25),
        ("kuramoto", "er", 10, 25),
        ("kuramoto", "ws", 10, 20),
        ("kuramoto", "er", 7, 18),  # round(17.5) = 18
    ],
)
def test_system_graph_sizes(name, topology, n, edge_count):
    a = get_system(name).graph(topology, n, seed=4)
    assert a.shape == (n, n) and a.dtype == np.uint8
    assert a.sum() // 2 == edge_count


def test_gene_er_density():
    a = get_system("gene").graph("er", 64, seed=0)
    assert abs(a.sum() / (64 * 63) - 0.5) < 0.03


def test_system_graph_errors():
    with pytest.raises(ValueError, match="choose from: ba, er, ws"):
        get_system("kuramoto").graph("chain", 10, seed=0)
    with pytest.raises(ValueError, match="more than 5 nodes"):
        get_system("kuramoto").graph("ba", 5, seed=0)


def test_registry():
    assert list(SYSTEMS) == ["pendulum", "lorenz", "gene", "kuramoto", "quadrotor",
                             "sis", "mak", "mm", "bd", "nd"]
    for name, cls in SYSTEMS.items():
        system = get_system(name)
        assert isinstance(system, cls) and system.name == name
        assert system.default_topology in system.topologies
        assert system.node_dim == len(system.state_names)
        assert system.control_dim == (5 if name == "quadrotor" else 0)
    expected = {
        "pendulum": {"m": 1.0, "l": 1.5, "k": 2.0, "g": 9.81},
        "lorenz": {"sigma": 10.0, "rho": 28.0, "beta": 8 / 3},
        "gene": {"b": 1.0, "f": 1.0, "h": 2.0},
        "kuramoto": {"K": 1 / 3},
    }
    for name, params in expected.items():
        assert get_system(name).scalar_params() == params


def test_registry_errors():
    with pytest.raises(ValueError, match=r"unknown system 'nope' \(choose from: pendulum, "):
        get_system("nope")
    with pytest.raises(ValueError, match="unknown parameter 'q'"):
        get_system("pendulum", q=1.0)
    with pytest.raises(ValueError, match="ic_range"):
        get_system("pendulum", ic_range="huge")
    with pytest.raises(ValueError, match="init"):
        get_system("gene", init="block")
    with pytest.raises(ValueError, match="coupling"):
        get_system("lorenz", coupling=-1.0)


# ----- trajectories: closed forms and scipy (integrated by our solver in float64) -------------


def _solve_system(system, graphs, y0, ts, params=None, rng=None):
    """Solve K trajectories at rtol 1e-10 / atol 1e-12; returns ys [K, T, N, D] and params."""
    rng = rng or np.random.default_rng(RNG_SEED)
    adjacency, stacked, per_graph = _torch_inputs(system, graphs, rng)
    if params is not None:  # override the drawn per-graph parameters
        stacked = {key: torch.from_numpy(np.stack(value)) for key, value in params.items()}
        per_graph = [{key: value[b] for key, value in params.items()} for b in range(len(graphs))]
    sol = solve(
        system.rhs(adjacency, stacked),
        torch.from_numpy(y0),
        torch.from_numpy(ts),
        rtol=1e-10,
        atol=1e-12,
    )
    assert sol.success.all()
    return sol.ys.numpy(), per_graph


def test_gene_without_edges_decays_exponentially():
    rng = np.random.default_rng(RNG_SEED)
    system = get_system("gene")
    graphs = np.zeros((4, 9, 9), np.uint8)
    x0 = system.sample_initial(graphs[0], 4, rng)
    ts = np.linspace(0.0, 5.0, 51)
    ys, _ = _solve_system(system, graphs, x0, ts)
    exact = x0[:, None] * np.exp(-ts)[None, :, None, None]  # [K, T, N, 1]
    np.testing.assert_allclose(ys, exact, rtol=1e-8, atol=1e-10)


def test_uncoupled_kuramoto_rotates_uniformly():
    rng = np.random.default_rng(RNG_SEED)
    system = get_system("kuramoto", K=0.0)
    graphs = np.stack([system.graph("ba", 10, seed=s) for s in range(3)])
    theta0 = system.sample_initial(graphs[0], 3, rng)
    ts = np.linspace(0.0, 2.5, 51)
    ys, params = _solve_system(system, graphs, theta0, ts, rng=rng)
    omega = np.stack([p["omega"] for p in params])  # [K, 3]
    exact = theta0[:, None] + ts[None, :, None, None] * omega[:, None, None, :]
    np.testing.assert_allclose(ys, exact, rtol=1e-9, atol=1e-9)


def test_two_kuramoto_nodes_phase_locking():
    # Δ = θ_2 − θ_1 obeys Δ̇ = −2K sin Δ, so tan(Δ/2) = tan(Δ_0/2) e^{−2Kt}; the mean phase
    # moves at ω.
    rng = np.random.default_rng(RNG_SEED)
    system = get_system("kuramoto")
    coupling = system.scalar_params()["K"]
    graphs = np.repeat(make_graph("complete", 2, seed=0)[None], 5, axis=0)
    theta0 = system.sample_initial(graphs[0], 5, rng)
    ts = np.linspace(0.0, 5.0, 101)
    ys, params = _solve_system(system, graphs, theta0, ts, rng=rng)
    omega = np.stack([p["omega"] for p in params])[:, None, :]  # [K, 1, 3]
    delta0 = theta0[:, 1] - theta0[:, 0]  # [K, 3]
    decay = np.exp(-2 * coupling * ts)[None, :, None]  # [1, T, 1]
    delta = 2 * np.arctan(np.tan(delta0[:, None] / 2) * decay)  # [K, T, 3]
    np.testing.assert_allclose(ys[:, :, 1] - ys[:, :, 0], delta, atol=1e-8)
    mean = theta0.mean(axis=1)[:, None] + omega * ts[None, :, None]
    np.testing.assert_allclose(ys.mean(axis=2), mean, atol=1e-8)


def _linear_chain_oscillator(a, y0, y_dot0, ts, p):
    """Closed form of m ÿ = −(m g/l) y − k L y (L = D − A), by normal modes.

    Returns y [T, N]."""
    m, length, k, g = p["m"], p["l"], p["k"], p["g"]
    a = a.astype(np.float64)
    stiffness = (g / length) * np.eye(len(a)) + (k / m) * (np.diag(a.sum(axis=1)) - a)
    lam, q = np.linalg.eigh(stiffness)  # modes q[:, r] with ω_r² = lam[r] > 0
    w = np.sqrt(lam)
    c0, c_dot0 = q.T @ y0, q.T @ y_dot0
    modes = c0 * np.cos(np.outer(ts, w)) + (c_dot0 / w) * np.sin(np.outer(ts, w))  # [T, N]
    return modes @ q.T


@pytest.mark.parametrize(("n", "m"), [(2, 1.0), (2, 2.0), (4, 1.0)])
def test_pendulum_is_a_linear_oscillator_in_l_sin_theta(n, m):
    rng = np.random.default_rng(RNG_SEED)
    system = get_system("pendulum", m=m)
    p = system.scalar_params()
    chain = make_graph("chain", n, seed=0)
    # Half the default box keeps |y| < l for all time, so θ stays off the singularity.
    x0 = 0.5 * system.sample_initial(chain, 4, rng)  # [K, N, 2]
    ts = np.linspace(0.0, 5.0, 51)  # two periods of the slowest mode (2π/√(g/l) ≈ 2.5 s)
    ys, _ = _solve_system(system, np.repeat(chain[None], 4, axis=0), x0, ts)
    assert not system.reject(ys).any()
    for b in range(4):
        theta0, theta_dot0 = x0[b, :, 0], x0[b, :, 1]
        y_exact = _linear_chain_oscillator(
            chain,
            p["l"] * np.sin(theta0),
            p["l"] * np.cos(theta0) * theta_dot0,  # ẏ = l cos θ θ̇
            ts,
            p,
        )
        np.testing.assert_allclose(p["l"] * np.sin(ys[b, :, :, 0]), y_exact, atol=1e-8)


def test_two_pendulum_normal_mode_frequencies():
    # The symmetric and antisymmetric modes of the paper's pair: √(g/l) and √(g/l + 2k/m).
    p = {"m": 1.0, "l": 1.5, "k": 2.0, "g": 9.81}
    w_s, w_a = math.sqrt(p["g"] / p["l"]), math.sqrt(p["g"] / p["l"] + 2 * p["k"] / p["m"])
    a = make_graph("chain", 2, seed=0)
    ts = np.array([0.0, 1.0])
    for sign, w in [(1.0, w_s), (-1.0, w_a)]:
        y = _linear_chain_oscillator(a, np.array([0.1, sign * 0.1]), np.zeros(2), ts, p)
        np.testing.assert_allclose(y[1], 0.1 * math.cos(w) * np.array([1.0, sign]), rtol=1e-12)


@pytest.mark.parametrize("coupling", [0.01, 1.0])
def test_lorenz_matches_scipy_dop853(coupling):
    rng = np.random.default_rng(RNG_SEED)
    system = get_system("lorenz", coupling=coupling)
    graphs = np.repeat(system.graph("complete", 3, seed=0)[None], 2, axis=0)
    x0 = system.sample_initial(graphs[0], 2, rng)
    ts = np.linspace(0.0, 2.5, 51)
    ys, params = _solve_system(system, graphs, x0, ts, rng=rng)
    for b in range(2):
        h = params[b]["coupling"]
        ref = solve_ivp(
            lambda t, x, h=h: _lorenz_ref(x.reshape(3, 3), h, 10.0, 28.0, 8 / 3).reshape(-1),
            (0.0, 2.5),
            x0[b].reshape(-1),
            method="DOP853",
            t_eval=ts,
            rtol=1e-12,
            atol=1e-12,
        )
        ref_ys = ref.y.T.reshape(len(ts), 3, 3)
        assert np.abs(ys[b] - ref_ys).max() / np.abs(ref_ys).max() < 1e-6


def test_registry_import_is_cheap():
    # The CLI lists systems for --help; that must not pay for torch or networkx.
    code = (
        "import sys, mpnode_cli.systems.registry; "
        "print(any(m in sys.modules for m in ('torch', 'networkx')))"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "False"


# ----- the same systems on edge lists (graphs above DENSE_GRAPH_MAX_NODES) --------------------


def _loop_ref(name: str, system: System, a: np.ndarray, y: np.ndarray, params: dict):
    """The right-hand side of one trajectory, from the loops above."""
    if name == "kuramoto":
        return _kuramoto_ref(a, y, params["omega"], system.params["K"])
    if name == "gene":
        return _gene_ref(a, y, *(system.params[key] for key in ("b", "f", "h")))
    return _pendulum_ref(a, y, system.params)


@pytest.mark.parametrize("shared", [True, False], ids=["shared", "per_trajectory"])
@pytest.mark.parametrize("name", ["kuramoto", "gene", "pendulum"])
def test_rhs_on_edges_equals_dense_and_the_loop(name, shared):
    from mpnode_cli.graphs.matrices import Graphs

    rng = np.random.default_rng(RNG_SEED)
    system = get_system(name)
    assert system.sparse
    graphs = _random_graphs(3, 8, rng)
    graphs[1, 2, :] = 0  # a node that hears nobody
    order = [1] * 5 if shared else BLOCKS
    per_graph = [system.graph_params(a, rng) for a in graphs]
    which = [order[0]] if shared else order
    params = {key: torch.from_numpy(np.stack([per_graph[g][key] for g in which]))
              for key in per_graph[0]}  # fmt: skip
    if name == "pendulum":  # away from cos θ = 0
        y = np.stack([rng.uniform(-1, 1, (len(order), 8)), rng.uniform(-2, 2, (len(order), 8))],
                     axis=-1)
    else:
        y = np.concatenate([system.sample_initial(graphs[g], 1, rng) for g in order])
    t = torch.zeros(len(order), dtype=torch.float64)
    edges = Graphs.from_adjacency(graphs).batch(np.asarray(which))
    dense = torch.from_numpy(graphs[which].astype(np.float64))  # [1 or K, N, N]
    sparse_out = system.rhs(edges, params)(t, torch.from_numpy(y))
    dense_out = system.rhs(dense, params)(t, torch.from_numpy(y))
    torch.testing.assert_close(sparse_out, dense_out, rtol=1e-13, atol=1e-12)
    for k, g in enumerate(order):
        one = {key: value[k if not shared else 0].numpy() for key, value in params.items()}
        np.testing.assert_allclose(sparse_out[k].numpy(), _loop_ref(name, system, graphs[g],
                                                                    y[k], one),
                                   rtol=1e-12, atol=1e-12)


@pytest.mark.parametrize("name", ["kuramoto", "gene"])
def test_trajectories_on_edges_equal_the_dense_ones(name):
    """A whole solve from edges (scatter sums) and from the matrix (GEMMs): the same
    trajectories up to rounding, on a Barabási–Albert graph of 40 nodes."""
    from mpnode_cli.graphs.matrices import Graphs
    from mpnode_cli.graphs.topologies import make_edges

    rng = np.random.default_rng(RNG_SEED)
    system = get_system(name)
    a = make_graph("ba", 40, seed=3, m=3)
    edge_list = make_edges("ba", 40, seed=3, m=3)
    np.testing.assert_array_equal(edge_list.to_dense(), a)  # the same graph either way
    params = {key: torch.from_numpy(v[None]) for key, v in system.graph_params(a, rng).items()}
    y0 = torch.from_numpy(system.sample_initial(a, 4, rng))
    ts = torch.linspace(0.0, 1.0, 11, dtype=torch.float64)
    dense = torch.from_numpy(a[None].astype(np.float64))
    edges = Graphs.from_edge_lists(40, [edge_list]).batch(np.zeros(1, np.int64))
    kwargs = {"rtol": 1e-9, "atol": 1e-11}
    by_matrix = solve(system.rhs(dense, params), y0, ts, **kwargs)
    by_edges = solve(system.rhs(edges, params), y0, ts, **kwargs)
    assert (by_edges.status == 0).all()
    torch.testing.assert_close(by_edges.ys, by_matrix.ys, rtol=1e-8, atol=1e-8)


def test_generate_above_the_threshold_runs_on_edges(tmp_path):
    """Kuramoto on 300 nodes (above DENSE_GRAPH_MAX_NODES): the file holds edges only, the
    graph is networkx's BA graph of the seed, and the states are those of a dense solve."""
    import h5py

    from mpnode_cli.config.generate import GenerateConfig
    from mpnode_cli.data.generate import generate
    from mpnode_cli.data.hdf5 import read_dataset
    from mpnode_cli.graphs.matrices import DENSE_GRAPH_MAX_NODES

    n = 300
    assert n > DENSE_GRAPH_MAX_NODES
    config = GenerateConfig(system="kuramoto", nodes=n, trajectories=3, t_end=0.2, dt=0.1,
                            seed=2, graph_seed=5, out=tmp_path / "k.h5", dtype="float64")
    generate(config)
    with h5py.File(tmp_path / "k.h5") as f:
        assert "graph/adjacency" not in f and f["graph/edges"].shape[0] == 2
    ds = read_dataset(tmp_path / "k.h5")
    a = make_graph("ba", n, seed=5, m=5)  # the same graph, as a matrix (fine at this size)
    np.testing.assert_array_equal(ds.graphs.edges(0).to_dense(), a)
    with pytest.raises(ValueError, match="edge lists"):
        ds.adjacency  # noqa: B018 (no N×N matrix above the threshold)
    system = get_system("kuramoto")
    y0 = system.sample_initial(a, 3, np.random.default_rng(2))  # the generator's draws
    omega = system.graph_params(a, np.random.default_rng([5, 0]))["omega"]
    sol = solve(system.rhs(torch.from_numpy(a[None].astype(np.float64)),
                           {"omega": torch.from_numpy(omega[None])}),
                torch.from_numpy(y0), torch.tensor([0.0, 0.1, 0.2], dtype=torch.float64),
                rtol=1e-8, atol=1e-10)
    np.testing.assert_allclose(ds.states, sol.ys.numpy(), rtol=1e-9, atol=1e-9)


def test_systems_that_need_the_matrix_are_refused_above_the_threshold():
    from mpnode_cli.config.generate import GenerateConfig
    from mpnode_cli.data.generate import resolve_generate_config

    with pytest.raises(ValueError, match=r"lorenz.*N×N matrix.*at most 256"):
        resolve_generate_config(GenerateConfig(system="lorenz", nodes=300, trajectories=2,
                                               t_end=0.1, dt=0.05))
