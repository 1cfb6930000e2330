"""Graph topologies: sizes, symmetry, degrees and edge counts from graph theory."""

from __future__ import annotations

import numpy as np
import pytest

from mpnode_cli.graphs.edge_files import read_edge_list
from mpnode_cli.graphs.matrices import edges
from mpnode_cli.graphs.topologies import TOPOLOGIES, make_graph

# One valid parameter set per topology.
CASES = {
    "complete": {},
    "chain": {},
    "er": {"p": 0.3},
    "ba": {"m": 3},
    "ws": {"k": 4, "p": 0.5},
    "s1": {"gamma": 2.5, "beta": 2.0, "mean_degree": 4.0},
}


def test_every_topology_has_a_case():
    assert set(CASES) == set(TOPOLOGIES)


@pytest.mark.parametrize("topology", TOPOLOGIES)
def test_shape_dtype_symmetry_diagonal(topology):
    a = make_graph(topology, 12, seed=3, **CASES[topology])
    assert a.shape == (12, 12)
    assert a.dtype == np.uint8
    assert set(np.unique(a)) <= {0, 1}
    np.testing.assert_array_equal(a, a.T)
    assert not a.diagonal().any()


@pytest.mark.parametrize("topology", TOPOLOGIES)
def test_same_seed_same_graph(topology):
    a = make_graph(topology, 20, seed=7, **CASES[topology])
    b = make_graph(topology, 20, seed=7, **CASES[topology])
    np.testing.assert_array_equal(a, b)


@pytest.mark.parametrize("topology", ["er", "ba", "ws"])
def test_different_seeds_differ(topology):
    a = make_graph(topology, 30, seed=0, **CASES[topology])
    b = make_graph(topology, 30, seed=1, **CASES[topology])
    assert (a != b).any()


def test_complete_degrees():
    a = make_graph("complete", 7, seed=0)
    np.testing.assert_array_equal(a.sum(axis=1), np.full(7, 6))


def test_chain_degrees_and_neighbours():
    n = 6
    a = make_graph("chain", n, seed=0)
    np.testing.assert_array_equal(a.sum(axis=1), [1, 2, 2, 2, 2, 1])
    for i in range(n - 1):
        assert a[i, i + 1] == a[i + 1, i] == 1
    assert a.sum() == 2 * (n - 1)


def test_ba_edge_count():
    # networkx starts from a star on m + 1 nodes (m edges), then each of the remaining
    # n - m - 1 nodes brings m edges: m (n - m) in all.
    n, m = 10, 5
    a = make_graph("ba", n, seed=0, m=m)
    assert a.sum() // 2 == m * (n - m) == 25
    assert (a.sum(axis=1)[m + 1 :] >= m).all()  # every node added after the star


def test_er_gnm_has_exactly_m_edges():
    for seed in range(5):
        assert make_graph("er", 10, seed=seed, m_edges=25).sum() // 2 == 25


def test_er_gnp_edge_density():
    n, p = 200, 0.1
    a = make_graph("er", n, seed=0, p=p)
    density = a.sum() / (n * (n - 1))
    assert abs(density - p) < 0.01  # binomial std is about 0.0015


def test_ws_mean_degree():
    # Rewiring moves edges but keeps their number, n·k/2.
    n, k = 10, 4
    a = make_graph("ws", n, seed=0, k=k, p=0.5)
    assert a.sum() == n * k
    assert a.sum(axis=1).mean() == k


@pytest.mark.parametrize(
    ("topology", "n", "kw"),
    [
        ("torus", 5, {}),
        ("complete", 5, {"p": 0.1}),
        ("er", 5, {}),
        ("er", 5, {"p": 0.1, "m_edges": 3}),
        ("er", 5, {"m_edges": 11}),
        ("er", 5, {"p": 1.5}),
        ("ba", 5, {"m": 5}),
        ("ba", 5, {}),
        ("ws", 5, {"k": 5, "p": 0.5}),
        ("chain", 0, {}),
    ],
)
def test_bad_requests_raise(topology, n, kw):
    with pytest.raises(ValueError):
        make_graph(topology, n, seed=0, **kw)


def test_unknown_topology_lists_valid_ones():
    with pytest.raises(ValueError, match="choose from: complete, chain, er, ba, ws"):
        make_graph("torus", 5, seed=0)


def test_edges_match_adjacency():
    a = make_graph("er", 15, seed=2, p=0.3)
    senders, receivers = edges(a)
    assert senders.dtype == receivers.dtype == np.int64
    assert len(senders) == a.sum()
    rebuilt = np.zeros_like(a)
    rebuilt[receivers, senders] = 1
    np.testing.assert_array_equal(rebuilt, a)


def test_edges_direction_on_a_directed_matrix():
    a = np.zeros((3, 3), dtype=np.uint8)
    a[2, 0] = 1  # node 0 sends to node 2
    senders, receivers = edges(a)
    np.testing.assert_array_equal(senders, [0])
    np.testing.assert_array_equal(receivers, [2])


def test_read_edge_list(tmp_path):
    path = tmp_path / "g.txt"
    path.write_text("# a triangle and a tail\n0 1\n1 2\n\n2,0  # comma works too\n3\t2\n1 0\n")
    a = read_edge_list(path)
    expected = np.zeros((4, 4), dtype=np.uint8)
    for i, j in [(0, 1), (1, 2), (2, 0), (3, 2)]:
        expected[i, j] = expected[j, i] = 1
    assert a.dtype == np.uint8
    np.testing.assert_array_equal(a, expected)


def test_read_edge_list_weights(tmp_path):
    # networkx's weighted edge list: weight 1 is an edge, weight 0 declares its nodes only.
    path = tmp_path / "w.txt"
    path.write_text("0 1 1\n1 2 1.0\n2 3 0\n")
    expected = np.zeros((4, 4), dtype=np.uint8)
    for i, j in [(0, 1), (1, 2)]:
        expected[i, j] = expected[j, i] = 1
    np.testing.assert_array_equal(read_edge_list(path), expected)
    directed = read_edge_list(path, directed=True)
    assert directed[1, 0] == 1 and directed[0, 1] == 0


def test_read_edge_list_of_weight_zero_only_has_no_edges(tmp_path):
    path = tmp_path / "zero.txt"
    path.write_text("0 1 0\n")
    with pytest.raises(ValueError, match="no edges"):
        read_edge_list(path)


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ("0 1\n1 2 1 4\n", "two node ids"),
        ("0 1\n1 2 3\n", "not 0 or 1"),
        ("0 1\n1 2 0.5\n", "unweighted"),
        ("0 1\n1 2 heavy\n", "must be a number"),
        ("0 x\n", "integers"),
        ("0 -1\n", "non-negative"),
        ("2 2\n", "self-loop"),
        ("# nothing\n\n", "no edges"),
    ],
)
def test_read_edge_list_errors(tmp_path, text, message):
    path = tmp_path / "bad.txt"
    path.write_text(text)
    with pytest.raises(ValueError, match=message):
        read_edge_list(path)


# ----- edge lists without matrices -----------------------------------------------------------


@pytest.mark.parametrize("topology", TOPOLOGIES)
def test_make_edges_is_make_graph_without_the_matrix(topology):
    from mpnode_cli.graphs.topologies import make_edges

    a = make_graph(topology, 12, seed=7, **CASES[topology])
    e = make_edges(topology, 12, seed=7, **CASES[topology])
    assert e.shape == (12, 12) and e.symmetric()
    senders, receivers = edges(a)  # the matrix's nonzero entries, row by row
    np.testing.assert_array_equal(e.senders, senders)
    np.testing.assert_array_equal(e.receivers, receivers)
    np.testing.assert_array_equal(e.in_degree(), a.sum(axis=1))


def test_read_edges_matches_read_edge_list(tmp_path):
    from mpnode_cli.graphs.edge_files import read_edges

    path = tmp_path / "g.txt"
    path.write_text("0 1\n1 2\n2 0\n3 2\n1 0\n")
    for directed in (False, True):
        e = read_edges(path, directed=directed)
        np.testing.assert_array_equal(e.to_dense(), read_edge_list(path, directed=directed))
        assert e.symmetric() is not directed


def test_edge_batch_lays_graphs_out_over_the_batch():
    """`EdgeBatch.flat` against a loop: trajectory b's edges shifted by b·N."""
    from mpnode_cli.graphs.matrices import EdgeList, Graphs

    lists = [EdgeList.build(4, [0, 1, 3], [1, 2, 0]), EdgeList.build(4, [2], [3]),
             EdgeList.build(4, [], [])]
    graphs = Graphs.from_edge_lists(4, lists)
    index = np.array([1, 0, 2, 1, 0])
    senders, receivers = graphs.batch(index).flat()
    want_s = [s + 4 * b for b, g in enumerate(index) for s in lists[g].senders]
    want_r = [r + 4 * b for b, g in enumerate(index) for r in lists[g].receivers]
    assert senders.tolist() == want_s and receivers.tolist() == want_r
    dense = graphs.batch(index).to_dense()
    for b, g in enumerate(index):
        np.testing.assert_array_equal(dense[b].numpy(), lists[g].to_dense())
    np.testing.assert_array_equal(graphs.in_degree()[index],
                                  graphs.batch(index).in_degree().numpy())


def test_graphs_refuse_matrices_above_the_threshold():
    from mpnode_cli.graphs.matrices import DENSE_GRAPH_MAX_NODES, Graphs
    from mpnode_cli.graphs.topologies import make_edges

    n = DENSE_GRAPH_MAX_NODES + 1
    graphs = Graphs.from_edge_lists(n, [make_edges("chain", n, seed=0)])
    assert isinstance(graphs.graph(0), type(graphs.edges(0)))  # systems get the edge list
    with pytest.raises(ValueError, match="edge lists"):
        graphs.dense()
    with pytest.raises(ValueError, match="edge list"):
        graphs.batch([0]).to_dense()
