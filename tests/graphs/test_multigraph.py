"""Multigraphs (`generate --hubs H --hub-multiplicity W`): hubs joined by parallel edges.

References are independent of the code under test: the data against scipy on the stored
matrix; the model's aggregation on a multigraph against the same nodes on a simple graph
where every parallel edge comes from its own copy of the sender (what a multiplicity
means); matrices against edge lists; and the file's version and checks.
"""

from __future__ import annotations

import h5py
import numpy as np
import pytest
import torch
from conftest import invoke, one_line_error
from scipy.integrate import solve_ivp

from mpnode_cli.data.hdf5 import read_dataset
from mpnode_cli.graphs.matrices import EdgeList, Graphs
from mpnode_cli.graphs.topologies import join_hubs, make_edges, make_graph
from mpnode_cli.models.aggregate import in_degree
from mpnode_cli.models.backend import strategy_for
from mpnode_cli.models.registry import build_model

F64 = torch.float64


def test_hubs_hear_every_node_w_times_both_ways():
    a = make_graph("ba", 9, seed=3, m=2)
    got = join_hubs(a, 2, multiplicity=4)
    hubs = np.flatnonzero(got.sum(axis=1) == 4 * 8)  # in-degree W·(N − 1)
    assert len(hubs) == 2
    np.testing.assert_array_equal(got, got.T)
    assert not got.diagonal().any()
    assert (got[:, hubs] == 4).sum() == 2 * 8  # every other node hears each hub 4 times
    others = np.setdiff1d(np.arange(9), hubs)
    np.testing.assert_array_equal(got[np.ix_(others, others)], a[np.ix_(others, others)])
    # The edge list of a multigraph repeats each message once per edge, and rebuilds it.
    e = EdgeList.from_adjacency(got)
    assert len(e) == got.sum()
    np.testing.assert_array_equal(e.to_dense(), got)
    np.testing.assert_array_equal(e.in_degree(), got.sum(axis=1))
    graphs = Graphs.from_adjacency(got[None])
    assert graphs.multigraph and not Graphs.from_adjacency(a[None]).multigraph
    with pytest.raises(ValueError, match="hub multiplicity must lie in"):
        join_hubs(make_edges("ba", 30, seed=2, m=2), 1, multiplicity=2)


def test_parallel_edges_aggregate_as_copies_of_the_sender():
    # A multigraph on n nodes against a simple graph where each of the w parallel edges
    # j → i comes from its own copy of j: the sums, means and degrees of the original
    # nodes agree, on both backends.
    g = np.random.default_rng(0)
    n = 6
    counts = g.integers(0, 4, size=(n, n)) * (1 - np.eye(n, dtype=np.int64))
    m = torch.randn(1, n, 3, dtype=F64, generator=torch.Generator().manual_seed(1))
    rows, senders = [], []
    for i in range(n):
        for j in range(n):
            rows += [i] * int(counts[i, j])
            senders += [j] * int(counts[i, j])
    big = n + len(senders)  # the originals, then one copy per parallel edge
    simple = torch.zeros(1, big, big, dtype=F64)
    copies = torch.zeros(1, big, 3, dtype=F64)
    copies[0, :n] = m[0]
    for e, (i, j) in enumerate(zip(rows, senders, strict=True)):
        simple[0, i, n + e] = 1
        copies[0, n + e] = m[0, j]
    multi = torch.as_tensor(counts, dtype=F64)[None]
    for backend in ("dense", "scatter"):
        got, ref = strategy_for(multi, backend), strategy_for(simple, backend)
        for op in ("sum", "mean"):
            assert torch.allclose(getattr(got, op)()(m), getattr(ref, op)()(copies)[:, :n],
                                  rtol=1e-12, atol=1e-12), (backend, op)
    assert torch.equal(in_degree(multi), in_degree(simple)[:, :n])


def test_an_mpnode_field_on_a_multigraph_is_the_field_with_copied_senders():
    torch.manual_seed(0)
    net = build_model("mpnode", {"node_dim": 1, "update": "affine", "aggregate": "sum",
                                 "message_init": "learned"}).double()
    with torch.no_grad():  # gains start at 0: give them values so that coupling shows
        net.net[-1].weight.normal_(0, 0.3)
    net.fit_statistics(None, 0.1, torch.ones(1, 3, 3))
    multi = torch.tensor([[[0, 3, 1], [3, 0, 0], [1, 0, 0]]], dtype=F64)
    # node 0 hears node 1 three times: copies 3 and 4 of node 1 stand for two of them
    simple = torch.tensor([[[0, 1, 1, 1, 1], [1, 1, 0, 0, 0], [1, 0, 0, 0, 0],
                            [1, 0, 0, 0, 0], [1, 0, 0, 0, 0]]], dtype=F64)
    simple[0, 1, 1] = 0
    simple[0, 1, 0] = 3  # node 1 hears node 0 three times either way
    z = torch.randn(1, 3, 1 + 3, dtype=F64)
    z5 = torch.cat([z, z[:, 1:2], z[:, 1:2]], dim=1)
    t = torch.zeros(1, dtype=F64)
    got = net.vector_field(multi)(t, z)[:, 0]
    ref = net.vector_field(simple)(t, z5)[:, 0]
    assert torch.allclose(got, ref, rtol=1e-12, atol=1e-12)
    plain = net.vector_field((multi > 0).to(F64))(t, z)[:, 0]
    assert not torch.allclose(got, plain, rtol=1e-6)  # the multiplicity matters


def test_generate_simulates_the_multigraph_as_scipy_does(tmp_path):
    out = tmp_path / "hubs.h5"
    result = invoke("generate", "gene", "--nodes", 9, "--topology", "ba", "--graphs", 3,
                    "--trajectories", 3, "--hubs", 2, "--hub-multiplicity", 5,
                    "--t-end", 2, "--dt", 0.5, "--dtype", "float64", "-o", out)
    assert result.exit_code == 0, result.output
    ds = read_dataset(out)
    adjacency = np.asarray(ds.adjacency)
    assert [int(a.max()) for a in adjacency] == [1, 3, 5]  # 1 … W over the graphs
    assert [int(a.sum(axis=1).max()) for a in adjacency] == [8, 24, 40]
    states, times = np.asarray(ds.states), np.asarray(ds.time)
    for k in range(3):
        a = adjacency[ds.graph_index[k]].astype(float)
        ref = solve_ivp(lambda _, x, a=a: -x + a @ (x**2 / (1 + x**2)), (0, 2),
                        states[k, 0, :, 0], t_eval=times, rtol=1e-10, atol=1e-12)
        np.testing.assert_allclose(ref.y.T, states[k, :, :, 0], rtol=1e-6, atol=1e-6)
    with h5py.File(out) as f:
        assert f.attrs["format_version"] == 4
    assert invoke("check", out).exit_code == 0
    assert "by up to 5 parallel edges" in invoke("info", out).output
    plain = tmp_path / "plain.h5"
    assert invoke("generate", "gene", "--nodes", 9, "--topology", "ba", "--trajectories", 1,
                  "--hubs", 2, "--t-end", 1, "--dt", 0.5, "-o", plain).exit_code == 0
    with h5py.File(plain) as f:
        assert f.attrs["format_version"] == 3  # readable by an mpnode before multigraphs


def test_a_version_3_file_may_not_hold_a_multigraph(tmp_path):
    out = tmp_path / "hubs.h5"
    assert invoke("generate", "gene", "--nodes", 9, "--topology", "ba", "--trajectories", 1,
                  "--hubs", 1, "--hub-multiplicity", 2, "--graphs", 1, "--t-end", 1,
                  "--dt", 0.5, "-o", out).exit_code == 0
    with h5py.File(out, "r+") as f:
        f.attrs["format_version"] = 3
    result = invoke("check", out)
    assert result.exit_code != 0 and "only 0 and 1" in result.output


@pytest.mark.parametrize(("extra", "message"), [
    (("--hub-multiplicity", 3), "give hubs too"),
    (("--hubs", 1, "--hub-multiplicity", 3, "--nodes", 300), "at most 256 nodes"),
    (("--hubs", 1, "--hub-multiplicity", 300), "hub_multiplicity"),
])
def test_what_cannot_be_is_one_line(tmp_path, extra, message):
    args = ["generate", "gene", "--topology", "ba", "--trajectories", 1, "--t-end", 1,
            "--dt", 0.5, "-o", tmp_path / "x.h5", *extra]
    if "--nodes" not in extra:
        args += ["--nodes", 9]
    result = invoke(*args)
    assert result.exit_code == 2
    assert message in one_line_error(result)
