"""The Barzel–Barabási systems (`sis`, `mak`, `mm`, `bd`, `nd`): right-hand sides against
numpy written from their equations, on matrices and on edge lists; generated datasets
against scipy; the graphs each topology gets; the hubs' states at the fixed point of a star;
and `mpnode generate` through the CLI."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from conftest import invoke
from scipy.integrate import solve_ivp

from mpnode_cli.config.generate import GenerateConfig
from mpnode_cli.data.generate import generate
from mpnode_cli.data.hdf5 import read_dataset
from mpnode_cli.graphs.matrices import Graphs
from mpnode_cli.graphs.topologies import TOPOLOGIES, make_graph
from mpnode_cli.solver import solve
from mpnode_cli.systems import get_system

NAMES = ["sis", "mak", "mm", "bd", "nd"]
RNG_SEED = 20130813
# Parameters away from the defaults (and from each other), so a swapped name shows.
ODD_PARAMS = {
    "sis": {"B": 0.8, "R": 0.6},
    "mak": {"F": 1.5, "B": 0.7, "R": 0.9},
    "mm": {"B": 1.3, "a": 1.2, "h": 2.5, "R": 0.7},
    "bd": {"B": 0.9, "b": 2.5, "a": 1.5, "R": 1.1},
    "nd": {"B": 1.3, "C": 0.7, "R": 0.4},
}


def _reference(name: str, p: dict[str, float], a: np.ndarray, x: np.ndarray) -> np.ndarray:
    """ẋ `[N]` of one state `x` `[N]` on the graph `a` `[N, N]`, from the equations."""
    if name == "sis":
        return -p["B"] * x + p["R"] * (1 - x) * (a @ x)
    if name == "mak":
        return p["F"] - p["B"] * x - p["R"] * x * (a @ x)
    if name == "mm":
        return -p["B"] * x ** p["a"] + p["R"] * (a @ (x ** p["h"] / (1 + x ** p["h"])))
    if name == "bd":
        return -p["B"] * x ** p["b"] + p["R"] * (a @ x ** p["a"])
    return -p["B"] * x + p["C"] * np.tanh(x) + p["R"] * (a @ np.tanh(x))


def _random_graphs(k: int, n: int, rng: np.random.Generator) -> np.ndarray:
    """K undirected graphs of density 0.3, uint8 `[K, N, N]`, node 0 of the first isolated."""
    upper = np.triu(rng.random((k, n, n)) < 0.3, 1)
    graphs = (upper | upper.transpose(0, 2, 1)).astype(np.uint8)
    graphs[0, 0, :] = graphs[0, :, 0] = 0
    return graphs


# ----- right-hand sides ----------------------------------------------------------------------


@pytest.mark.parametrize("shared", [True, False], ids=["shared", "per_trajectory"])
@pytest.mark.parametrize("name", NAMES)
def test_rhs_on_matrices_and_edges_equals_the_equation(name, shared):
    rng = np.random.default_rng(RNG_SEED)
    system = get_system(name, **ODD_PARAMS[name])
    assert system.sparse and system.state_names == ("x",)
    graphs = _random_graphs(3, 12, rng)
    order = [0] * 4 if shared else [0, 0, 1, 1, 2, 2]  # each trajectory's graph
    which = order[:1] if shared else order
    y = np.concatenate([system.sample_initial(graphs[g], 1, rng) for g in order])
    t = torch.zeros(len(order), dtype=torch.float64)
    dense = torch.from_numpy(graphs[which].astype(np.float64))  # [1 or K, N, N]
    edges = Graphs.from_adjacency(graphs).batch(np.asarray(which))
    by_matrix = system.rhs(dense, {})(t, torch.from_numpy(y))
    by_edges = system.rhs(edges, {})(t, torch.from_numpy(y))
    torch.testing.assert_close(by_edges, by_matrix, rtol=1e-13, atol=1e-12)
    for k, g in enumerate(order):
        want = _reference(name, system.params, graphs[g].astype(np.float64), y[k, :, 0])
        np.testing.assert_allclose(by_edges[k, :, 0].numpy(), want, rtol=1e-12, atol=1e-12)


def test_parameters_and_initial_states():
    expected = {"sis": {"B": 1.0, "R": 0.3}, "mak": {"F": 1.0, "B": 1.0, "R": 1.0},
                "mm": {"B": 1.0, "a": 1.0, "h": 2.0, "R": 1.0},
                "bd": {"B": 1.0, "b": 2.0, "a": 1.0, "R": 1.0},
                "nd": {"B": 1.0, "C": 1.0, "R": 1.0}}
    boxes = {"sis": (0, 1), "mak": (0, 2), "mm": (0, 10), "bd": (0, 10), "nd": (-1, 1)}
    for name in NAMES:
        system = get_system(name)
        graph = {"gamma": 2.5, "beta": 2.5, "mean_degree": 10.0}
        assert system.scalar_params() == {**expected[name], **graph}
        assert (system.default_topology, system.topologies) == ("s1", ("s1", "er", "ba", "ws"))
        x0 = system.sample_initial(np.zeros((50, 50)), 40, np.random.default_rng(0))
        low, high = boxes[name]
        assert x0.shape == (40, 50, 1) and low <= x0.min() and x0.max() <= high
        assert x0.min() < low + 0.1 * (high - low) and x0.max() > high - 0.1 * (high - low)


# ----- graphs ------------------------------------------------------------------------------------


def test_graph_kwargs_give_the_mean_degree():
    system = get_system("sis", mean_degree=8, gamma=2.2, beta=3.0)
    assert system.graph_kwargs("s1", 100) == {"gamma": 2.2, "beta": 3.0, "mean_degree": 8.0}
    assert system.graph_kwargs("er", 101) == {"p": 8 / 100}
    assert system.graph_kwargs("ba", 100) == {"m": 4}
    assert system.graph_kwargs("ws", 100) == {"k": 8, "p": 0.1}
    # Small graphs: at most the complete graph; the ring's degree even and below n.
    small = get_system("mm")  # mean degree 10
    assert small.graph_kwargs("er", 6) == {"p": 1.0}
    assert small.graph_kwargs("ba", 6) == {"m": 5}
    assert small.graph_kwargs("ws", 6) == {"k": 4, "p": 0.1}
    for topology, tolerance in (("er", 0.5), ("ba", 0.2), ("ws", 0.0)):
        degrees = get_system("bd").graph(topology, 600, seed=1).in_degree()  # an EdgeList
        assert abs(degrees.mean() - 10) <= tolerance, (topology, degrees.mean())
    with pytest.raises(ValueError, match="mean_degree must be > 0"):
        get_system("nd", mean_degree=0).graph("er", 10, seed=0)
    with pytest.raises(ValueError, match="choose from: s1, er, ba, ws"):
        get_system("nd").graph("chain", 10, seed=0)


# ----- generated datasets against scipy ----------------------------------------------------------

S1 = pytest.mark.skipif("s1" not in TOPOLOGIES, reason="no s1 topology yet")


@pytest.mark.parametrize(("name", "topology"), [
    ("sis", "er"), ("mak", "ba"), ("mm", "ws"), ("bd", "er"), ("nd", "ba"),
    pytest.param("mm", "s1", marks=S1)])
def test_generated_trajectories_match_scipy(tmp_path, name, topology):
    """`generate` (float64, its default tolerances) against DOP853 at rtol 1e-10, atol 1e-12,
    from the stored initial states on the stored graph, to 1e-6 of the largest state."""
    n = 64 if topology == "s1" else 24
    config = GenerateConfig(system=name, nodes=n, topology=topology, trajectories=3,
                            graph_seed=5, seed=2, dtype="float64", out=tmp_path / "d.h5")
    ds = read_dataset(generate(config).path)
    system = get_system(name)
    a = make_graph(topology, n, 5, **system.graph_kwargs(topology, n))
    np.testing.assert_array_equal(ds.graphs.graph(0), a)  # the graph the kwargs give
    assert ds.scalar_params == system.scalar_params()
    ts, states, a = ds.time, ds.states, a.astype(np.float64)
    assert ts[-1] == system.data_defaults["t_end"] and len(ts) == 101
    for k in range(3):
        ref = solve_ivp(lambda t, x: _reference(name, system.params, a, x), (0.0, ts[-1]),
                        states[k, 0, :, 0], method="DOP853", t_eval=ts, rtol=1e-10,
                        atol=1e-12)
        assert ref.success
        scale = np.abs(ref.y).max()
        assert np.abs(states[k, :, :, 0] - ref.y.T).max() / scale < 1e-6


# ----- properties --------------------------------------------------------------------------------


def _solve(system, a: np.ndarray, x0: np.ndarray, t_end: float, steps: int = 11) -> np.ndarray:
    """States `[K, T, N]` from `x0` `[K, N]` on the graph `a`, at rtol 1e-10, atol 1e-12."""
    ts = torch.linspace(0.0, t_end, steps, dtype=torch.float64)
    sol = solve(system.rhs(torch.from_numpy(a[None].astype(np.float64)), {}),
                torch.from_numpy(x0[..., None]), ts, rtol=1e-10, atol=1e-12)
    assert sol.success.all()
    return sol.ys[..., 0].numpy()


@pytest.mark.parametrize("r", [0.02, 2.0], ids=["dies_out", "hubs_near_1"])
def test_sis_stays_in_the_unit_interval(r):
    system = get_system("sis", R=r)
    a = make_graph("ba", 40, 3, m=3)
    x0 = np.random.default_rng(RNG_SEED).uniform(0, 1, (4, 40))
    x0[0] = 1.0  # all infected
    x0[1, ::2] = 0.0  # half healthy
    ys = _solve(system, a, x0, 10.0, steps=101)
    assert ys.min() >= 0.0 and ys.max() <= 1.0
    assert (ys[:, -1].max() < 1e-3) if r < 0.1 else (ys[:, -1].min() > 0.5)


def _star(leaves: int) -> np.ndarray:
    """A star: node 0 the centre, nodes 1..leaves its leaves, uint8 `[leaves + 1]²`."""
    a = np.zeros((leaves + 1, leaves + 1), np.uint8)
    a[0, 1:] = a[1:, 0] = 1
    return a


@pytest.mark.parametrize("name", ["mm", "bd", "mak", "sis", "nd"])
def test_hubs_at_the_fixed_point_of_a_star(name):
    """The centre of a star (degree 8) against its leaves (degree 1) at the steady state:
    higher for mm, bd, sis (and |x| for nd), lower for mak; bd's is n^{2/3} against
    n^{1/3} (x_c² = 8·x_l, x_l² = x_c at b = 2, a = 1)."""
    # sis: R above the star's threshold 1/√8 ≈ 0.35 (the default 0.3 dies out on it).
    system = get_system(name, **({"R": 1.0} if name == "sis" else {}))
    a = _star(8)
    x0 = system.sample_initial(a, 3, np.random.default_rng(RNG_SEED))[..., 0]
    x0[:, 0] = np.abs(x0[:, 0]) + 0.5  # a centre away from 0 (nd's slow start, mm's off state)
    x0[:, 1:] = np.abs(x0[:, 1:]) + 0.5
    end = _solve(system, a, x0, 40.0)[:, -1]  # [K, N]
    rate = system.rhs(torch.from_numpy(a[None].astype(np.float64)), {})(
        torch.zeros(3, dtype=torch.float64), torch.from_numpy(end[..., None]))
    assert rate.abs().max() < 1e-6  # settled
    np.testing.assert_allclose(end[:, 1:], end[:, 1:2].repeat(8, axis=1), rtol=1e-8)
    centre, leaf = np.abs(end[:, 0]), np.abs(end[:, 1])
    if name == "mak":
        assert (centre < leaf).all()
    else:
        assert (centre > leaf).all()
    if name == "bd":
        np.testing.assert_allclose(end[:, 0], 4.0, rtol=1e-8)
        np.testing.assert_allclose(end[:, 1], 2.0, rtol=1e-8)


def test_nd_states_stay_within_their_bound():
    """|x_i| ≤ max(|x_i(0)|, (C + R·k_i)/B): beyond it, |x_i| falls (|tanh| ≤ 1)."""
    system = get_system("nd", B=1.5, C=2.0, R=0.8)
    a = make_graph("ba", 40, 4, m=2)
    x0 = system.sample_initial(a, 4, np.random.default_rng(RNG_SEED))[..., 0] * 20
    ys = _solve(system, a, x0, 10.0, steps=101)
    bound = np.maximum(np.abs(x0), (2.0 + 0.8 * a.sum(axis=1)) / 1.5)  # [K, N]
    assert (np.abs(ys) <= bound[:, None] + 1e-9).all()


# ----- the command -------------------------------------------------------------------------------


def test_mpnode_generate_sis(tmp_path):
    out = tmp_path / "sis.h5"
    result = invoke("generate", "sis", "--nodes", 16, "--topology", "er", "--trajectories", 4,
                    "-p", "R=0.5", "-p", "mean_degree=6", "-o", out)
    assert result.exit_code == 0, result.output
    ds = read_dataset(out)
    assert ds.system == "sis" and ds.states.shape == (4, 101, 16, 1)
    assert ds.scalar_params["R"] == 0.5 and ds.scalar_params["mean_degree"] == 6.0
    assert 0.0 <= ds.states.min() and ds.states.max() <= 1.0
    shown = " ".join(invoke("generate", "--help").output.replace("│", " ").split())
    assert "sis, mak, mm, bd, nd" in shown and "s1" in shown
