"""Neighbour aggregation (mean, sum, PNA; dense and scatter) against loops written from the
definitions, and permutation equivariance."""

from __future__ import annotations

import math

import pytest
import torch

from mpnode_cli.models.aggregate import (
    AGGREGATES,
    aggregator,
    channels,
    in_degree,
    mean_log_degree,
)

pytestmark = pytest.mark.usefixtures("float64_default")


def random_graph(batch: int, nodes: int, p: float, seed: int) -> torch.Tensor:
    gen = torch.Generator().manual_seed(seed)
    a = (torch.rand(batch, nodes, nodes, generator=gen) < p).double()
    return a * (1 - torch.eye(nodes))


def loop_reference(adj: torch.Tensor, m: torch.Tensor, how: str, delta: float | None):
    """Node by node, from the definitions (Corso et al. 2020, eqs. 4–5 for PNA)."""
    batch, nodes, feats = m.shape
    out = torch.zeros(batch, nodes, channels(how, feats))
    for b in range(batch):
        for i in range(nodes):
            # an edge of multiplicity w is w neighbours (a multigraph)
            nbrs = [j for j in range(nodes) for _ in range(int(adj[b, i, j]))]
            if not nbrs:
                continue  # an isolated node receives zeros
            total = sum(m[b, j] for j in nbrs)
            mean = total / len(nbrs)
            if how == "sum":
                out[b, i] = total
            elif how == "mean":
                out[b, i] = mean
            else:
                log_d = math.log(len(nbrs) + 1)
                out[b, i] = torch.cat([mean, mean * log_d / delta, mean * delta / log_d])
    return out


@pytest.mark.parametrize("how", AGGREGATES)
@pytest.mark.parametrize("backend", ["dense", "scatter"])
def test_aggregation_matches_its_definition(how, backend):
    adj = random_graph(3, 7, 0.4, seed=2)
    adj[1, 4, :] = 0.0  # node 4 of graph 1 hears nobody
    adj[2, 0, 3] = 3.0  # an edge of multiplicity 3 counts three times
    m = torch.randn(3, 7, 5)
    delta = 1.3
    got = aggregator(adj, how, backend, delta)(m)
    torch.testing.assert_close(got, loop_reference(adj, m, how, delta))
    assert torch.equal(got[1, 4], torch.zeros(channels(how, 5)))


@pytest.mark.parametrize("how", AGGREGATES)
def test_aggregation_is_permutation_equivariant(how):
    adj = random_graph(2, 9, 0.3, seed=5)
    m = torch.randn(2, 9, 4)
    perm = torch.randperm(9, generator=torch.Generator().manual_seed(1))
    agg = aggregator(adj, how, "auto", 0.9)(m)
    agg_p = aggregator(adj[:, perm][:, :, perm], how, "auto", 0.9)(m[:, perm])
    torch.testing.assert_close(agg_p, agg[:, perm])


def test_degree_statistics():
    adj = torch.zeros(1, 4, 4)
    adj[0, 0, 1:] = 1.0  # node 0 hears 3 nodes, node 1 hears one, the rest none
    adj[0, 1, 0] = 1.0
    torch.testing.assert_close(in_degree(adj), torch.tensor([[3.0, 1.0, 0.0, 0.0]]))
    assert mean_log_degree(adj) == pytest.approx((math.log(4) + math.log(2)) / 4)


def test_degree_statistic_of_several_datasets_pools_their_nodes():
    """Graphs of 4 and 2 nodes (two datasets): δ is the mean over all 4 + 2·2 nodes, not the
    mean of the two datasets' means."""
    four = torch.zeros(1, 4, 4)
    four[0, 0, 1:] = 1.0  # degrees 3, 0, 0, 0
    two = torch.ones(2, 2, 2) - torch.eye(2)  # degrees 1, 1 in both graphs
    expected = (math.log(4) + 4 * math.log(2)) / 8
    assert mean_log_degree([four, two]) == pytest.approx(expected)
    assert mean_log_degree([four]) == mean_log_degree(four)


def test_pna_needs_a_fitted_degree_statistic():
    adj = random_graph(1, 4, 0.5, seed=0)
    with pytest.raises(ValueError, match="δ"):
        aggregator(adj, "pna", "dense", None)
    with pytest.raises(ValueError, match="positive"):
        aggregator(adj, "pna", "dense", 0.0)


def test_sum_lets_a_node_sense_its_degree_and_mean_does_not():
    """The property that motivates `sum`: equal messages, different in-degrees."""
    adj = torch.zeros(1, 3, 3)
    adj[0, 0, 1] = 1.0
    adj[0, 2, :2] = 1.0
    m = torch.ones(1, 3, 1)
    assert aggregator(adj, "mean", "dense")(m)[0, [0, 2], 0].tolist() == [1.0, 1.0]
    assert aggregator(adj, "sum", "dense")(m)[0, [0, 2], 0].tolist() == [1.0, 2.0]


# ----- from edge lists (what large graphs are): no [N, N] matrix on the scatter path ------------


def random_edges(graphs: int, nodes: int, edges: int, seed: int):
    """`graphs` random directed graphs as edge lists (duplicates merged, self-loops dropped),
    and the same graphs as matrices written entry by entry: (Graphs, [G, N, N])."""
    import numpy as np

    from mpnode_cli.graphs.matrices import EdgeList, Graphs

    rng = np.random.default_rng(seed)
    lists, mats = [], torch.zeros(graphs, nodes, nodes)
    for g in range(graphs):
        s, r = rng.integers(0, nodes, edges), rng.integers(0, nodes, edges)
        keep = s != r
        lists.append(EdgeList.build(nodes, s[keep], r[keep]))
        for j, i in zip(s[keep], r[keep], strict=True):
            mats[g, i, j] = 1.0
    return Graphs.from_edge_lists(nodes, lists), mats


@pytest.mark.parametrize("how", AGGREGATES)
@pytest.mark.parametrize("backend", ["auto", "dense", "scatter"])
def test_aggregation_from_edges_matches_its_definition_and_the_dense_path(how, backend):
    import numpy as np

    graphs, mats = random_edges(3, 7, 12, seed=4)
    graph_index = np.array([2, 0, 0, 1, 2])  # graphs shared and out of order
    edges = graphs.batch(graph_index)
    adj = mats[graph_index]  # [5, 7, 7]
    assert (adj.sum(dim=2) == 0).any()  # some node hears nobody
    m = torch.randn(5, 7, 4)
    got = aggregator(edges, how, backend, 1.1)(m)
    torch.testing.assert_close(got, loop_reference(adj, m, how, 1.1))
    torch.testing.assert_close(got, aggregator(adj, how, "dense", 1.1)(m))
    torch.testing.assert_close(in_degree(edges), adj.sum(dim=2))
    assert mean_log_degree(edges) == pytest.approx(float(torch.log1p(adj.sum(dim=2)).mean()))


@pytest.mark.parametrize("how", AGGREGATES)
def test_aggregation_from_edges_is_permutation_equivariant(how):
    import numpy as np

    from mpnode_cli.graphs.matrices import EdgeList, Graphs

    graphs, _ = random_edges(1, 9, 20, seed=6)
    perm = np.random.default_rng(1).permutation(9)  # new node q is old node perm[q]
    inv = np.argsort(perm)
    old = graphs.edges(0)
    relabelled = Graphs.from_edge_lists(9, [EdgeList.build(9, inv[old.senders],
                                                           inv[old.receivers])])
    m = torch.randn(2, 9, 3)
    index = np.zeros(2, np.int64)
    agg = aggregator(graphs.batch(index), how, "scatter", 0.8)(m)
    agg_p = aggregator(relabelled.batch(index), how, "scatter", 0.8)(m[:, perm])
    torch.testing.assert_close(agg_p, agg[:, perm])


def test_large_graphs_aggregate_without_a_matrix():
    """1 000 nodes: the scatter path runs from the edges; asking for matrices is refused."""
    from mpnode_cli.graphs.matrices import Graphs
    from mpnode_cli.graphs.topologies import make_edges
    from mpnode_cli.models.aggregate import full_graph

    chain = make_edges("chain", 1000, seed=0)
    edges = Graphs.from_edge_lists(1000, [chain]).batch([0, 0])
    m = torch.arange(2 * 1000, dtype=torch.float64).reshape(2, 1000, 1)
    got = aggregator(edges, "sum", "auto")(m)
    want = torch.zeros_like(m)  # a path: node i hears i − 1 and i + 1
    want[:, 1:] += m[:, :-1]
    want[:, :-1] += m[:, 1:]
    torch.testing.assert_close(got, want)
    with pytest.raises(ValueError, match="at most 256"):
        aggregator(edges, "mean", "dense")
    with pytest.raises(ValueError, match="graph 'sys'"):
        full_graph(edges)


def test_the_registries_are_the_declared_choices():
    """`options.Aggregate` and `options.Backend` are the one declared list of names (the CLI
    and configs offer them): every name has its class and every class its name."""
    from typing import get_args

    from mpnode_cli.models.aggregate import AGGREGATIONS
    from mpnode_cli.models.backend import STRATEGIES
    from mpnode_cli.models.options import Aggregate, Backend

    assert tuple(AGGREGATIONS) == get_args(Aggregate)
    assert all(kind.name == name for name, kind in AGGREGATIONS.items())
    assert set(STRATEGIES) | {"auto"} == set(get_args(Backend))
    assert [channels(how, 5) for how in AGGREGATES] == [5, 5, 15]


# ----- aggregations as modules: PNA owns its δ, fitted once; old checkpoints move it -------------

@pytest.mark.parametrize("kind", ["mpnode", "gnode"])
def test_pna_owns_its_degree_statistic_fitted_once_on_every_training_graph(kind):
    """δ is PNA's buffer, fitted on every training graph (two datasets' of other sizes
    pooled over their nodes, by hand from the degrees), once; the other aggregations keep
    no statistic."""
    from mpnode_cli.models.registry import build_model

    small, large = random_graph(3, 4, 0.5, seed=1), random_graph(2, 7, 0.4, seed=2)
    degrees = [d for a in (small, large) for d in a.sum(dim=2).flatten().tolist()]
    model = build_model(kind, {"node_dim": 1, "aggregate": "pna"})
    assert [k for k in model.state_dict() if "delta" in k] == ["aggregation.delta"]
    model.fit_statistics(None, 0.1, [small, large])
    expected = sum(math.log(1 + d) for d in degrees) / len(degrees)
    assert float(model.aggregation.delta) == pytest.approx(expected, rel=1e-12)
    model.fit_statistics(None, 0.1, large)  # a finetune keeps its parent's
    assert float(model.aggregation.delta) == pytest.approx(expected, rel=1e-12)
    for how in ("mean", "sum"):
        other = build_model(kind, {"node_dim": 1, "aggregate": how})
        other.fit_statistics(None, 0.1, small)
        assert not [k for k in other.state_dict() if "delta" in k]


@pytest.mark.parametrize("how", ["pna", "sum"])
def test_a_version_7_checkpoint_with_the_models_delta_reads_as_before(how, tmp_path):
    """Version 7 kept δ as the model's `degree_delta` whatever it aggregated with: PNA's
    moves into its module, the others' goes, and the weights load and predict as saved."""
    from mpnode_cli.models.registry import build_model
    from mpnode_cli.training.checkpoint_upgrade import upgrade_payload

    model = build_model("mpnode", {"node_dim": 1, "aggregate": how})
    adj = random_graph(2, 5, 0.5, seed=3)
    model.fit_statistics(None, 0.1, adj)
    state = {k: v.clone() for k, v in model.state_dict().items()}
    old = {k: v for k, v in state.items() if k != "aggregation.delta"}
    old["degree_delta"] = state.get("aggregation.delta", torch.tensor(0.7, dtype=torch.float64))
    payload = {"format": "mpnode-checkpoint", "format_version": 7, "model_kind": "mpnode",
               "model_config": model.config, "state_dict": old}
    upgrade_payload(payload, 7)
    assert payload["state_dict"].keys() == state.keys()
    for key, value in state.items():
        assert torch.equal(payload["state_dict"][key], value)


def test_a_version_7_file_loads_through_the_reader(user_files, tmp_path):
    """A whole checkpoint as version 7 wrote it (with the model's `degree_delta`) loads,
    and its model takes the weights (a strict load)."""
    from mpnode_cli.training.checkpoint import load_checkpoint

    raw = torch.load(user_files["checkpoint"], weights_only=True)
    now = set(raw["state_dict"])
    raw["format_version"] = 7
    raw.pop("payload_sha256")  # version 7 carried no digest
    raw["state_dict"]["degree_delta"] = torch.tensor(0.9, dtype=torch.float64)
    torch.save(raw, tmp_path / "v7.pt")
    ckpt = load_checkpoint(tmp_path / "v7.pt")
    assert set(ckpt.state_dict) == now
    assert ckpt.build_model().config == raw["model_config"]
