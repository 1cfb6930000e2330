"""Degree coverage (`generate --hubs`): hubs joined to every other node.

The reference graph is built with networkx from the same topology, by adding each hub's
edges to all others, not with `mpnode_cli.graphs.topologies.join_hubs`.
"""

from __future__ import annotations

import networkx as nx
import numpy as np
from conftest import invoke, one_line_error

from mpnode_cli.data.hdf5 import read_dataset
from mpnode_cli.graphs.matrices import EdgeList, edges
from mpnode_cli.graphs.topologies import join_hubs, make_edges, make_graph


def _reference(adjacency: np.ndarray, hubs: int) -> np.ndarray:
    """The hubs, by networkx's degree (highest first, lowest index among equals), joined to
    every other node."""
    g = nx.from_numpy_array(adjacency)
    by_degree = sorted(g.nodes, key=lambda v: (-g.degree[v], v))[:hubs]
    g.add_edges_from((h, v) for h in by_degree for v in g.nodes if v != h)
    return nx.to_numpy_array(g, nodelist=range(len(adjacency)), dtype=np.uint8)


def test_hubs_reach_every_node_and_keep_the_graph():
    a = make_graph("s1", 40, seed=5, gamma=2.5, beta=2.5, mean_degree=4.0)
    for hubs in (0, 1, 3, 40):
        got = join_hubs(a, hubs)
        np.testing.assert_array_equal(got, _reference(a, hubs))
        assert (got >= a).all()  # nothing removed
        np.testing.assert_array_equal(got, got.T)
        assert not got.diagonal().any()
        assert (got.sum(axis=1) == 39).sum() >= hubs  # in-degree N − 1 for every hub


def test_edge_lists_get_the_same_hubs_as_matrices():
    a = make_graph("ba", 30, seed=2, m=2)
    e = make_edges("ba", 30, seed=2, m=2)
    got = join_hubs(e, 4)
    assert isinstance(got, EdgeList)
    senders, receivers = edges(join_hubs(a, 4))
    np.testing.assert_array_equal(got.senders, senders)
    np.testing.assert_array_equal(got.receivers, receivers)


def test_generate_hubs_writes_them_and_refuses_what_cannot_be(tmp_path):
    out = tmp_path / "hubs.h5"
    result = invoke("generate", "sis", "--nodes", 12, "--topology", "er", "--graphs", 2,
                    "--trajectories", 2, "--t-end", 0.2, "--dt", 0.1, "--hubs", 2, "-o", out)
    assert result.exit_code == 0, result.output
    ds = read_dataset(out)
    adjacency = np.asarray(ds.adjacency)
    assert adjacency.shape == (2, 12, 12)
    for a in adjacency:
        assert (a.sum(axis=1) == 11).sum() >= 2
    assert "hubs joined to all" in invoke("info", out).output
    edge_list = tmp_path / "ring.txt"
    edge_list.write_text("".join(f"{i} {(i + 1) % 5}\n" for i in range(5)))
    assert "edge list" in one_line_error(invoke(
        "generate", "sis", "--edge-list", edge_list, "--hubs", 1, "-o", tmp_path / "x.h5"))
    assert "at most nodes" in one_line_error(invoke(
        "generate", "sis", "--nodes", 4, "--hubs", 5, "-o", tmp_path / "y.h5"))
