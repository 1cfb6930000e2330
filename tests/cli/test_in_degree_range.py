"""The in-degree range `info` and `check` show: min, median and max over every node of every
graph in a file, a multigraph's parallel edges counted by multiplicity, each graph once
however many trajectories run on it.

The references are independent of `mpnode_cli.graphs.matrices`: networkx's in-degrees of the graphs
rebuilt from the file's raw arrays, or in-degrees known by construction.
"""

from __future__ import annotations

import json
import re

import h5py
import networkx as nx
import numpy as np
from conftest import invoke

from mpnode_cli.graphs.matrices import degree_range


def _reported(path) -> tuple[dict, dict]:
    """The in-degree range of `info --json` and of `check --json`, after both exit 0."""
    info, check = invoke("info", path, "--json"), invoke("check", path, "--json")
    assert info.exit_code == 0 and check.exit_code == 0, info.output + check.output
    return json.loads(info.output)["in_degree"], json.loads(check.output)["summary"]["in_degree"]


def _shown(path) -> tuple[str, str]:
    """The text `info`'s table and `check`'s summary show for the range."""
    info, check = invoke("info", path).output, invoke("check", path).output
    row = re.search(r"in-degree\s*│?\s*(min [^│(]*)", info)
    line = re.search(r"^\s*in_degree: (.*)$", check, flags=re.M)
    assert row and line, info + check
    return row.group(1).strip(), line.group(1).strip()


def _expected(degrees: np.ndarray) -> dict:
    return {"min": int(degrees.min()), "median": float(np.median(degrees)),
            "max": int(degrees.max())}


def _networkx_in_degrees(path) -> np.ndarray:
    """Every node's in-degree in every graph of a file, from its raw `graph/edges` and
    `graph/num_edges` through a networkx MultiDiGraph (parallel edges kept)."""
    with h5py.File(path) as f:
        n = f["states"].shape[2]
        edges, counts = f["graph/edges"][()], f["graph/num_edges"][()]
    degrees, start = [], 0
    for count in counts:
        g = nx.MultiDiGraph()
        g.add_nodes_from(range(n))
        g.add_edges_from(zip(edges[0, start:start + count].tolist(),
                             edges[1, start:start + count].tolist(), strict=True))
        degrees.append([g.in_degree(v) for v in range(n)])
        start += count
    return np.array(degrees)


def test_the_range_is_that_of_every_entry():
    rng = np.random.default_rng(0)
    for _ in range(200):
        degrees = rng.integers(0, rng.integers(1, 30), size=(rng.integers(1, 6), 7))
        assert degree_range(degrees) == _expected(degrees)


def test_a_multigraph_counts_parallel_edges(tmp_path):
    """Hubs joined by 1, 2 and 3 parallel edges over the three graphs: the last graph's hubs
    hear 3·(N − 1) messages, three times what counting senders would give."""
    out, n = tmp_path / "multi.h5", 9
    result = invoke("generate", "gene", "--nodes", n, "--topology", "ba", "--graphs", 3,
                    "--trajectories", 3, "--hubs", 2, "--hub-multiplicity", 3,
                    "--t-end", 1, "--dt", 0.5, "-o", out)
    assert result.exit_code == 0, result.output
    degrees = _networkx_in_degrees(out)
    assert degrees.shape == (3, n) and degrees.max() == 3 * (n - 1)
    want = _expected(degrees)
    assert _reported(out) == (want, want)
    text = f"min {want['min']}, median {want['median']:g}, max {want['max']}"
    assert _shown(out) == (text, text)


def test_imported_graphs_each_count_once_not_per_trajectory(tmp_path):
    """Three trajectories on two distinct graphs (the first used twice): the median is over
    the 2 × 5 nodes of the graphs; weighted by trajectories it would be 1."""
    n = 5
    sparse = np.zeros((n, n), np.uint8)
    for sender, receiver in [(0, 1), (0, 2), (0, 3), (1, 2), (3, 2)]:
        sparse[receiver, sender] = 1  # in-degrees 0, 1, 3, 1, 0
    full = np.ones((n, n), np.uint8) - np.eye(n, dtype=np.uint8)  # in-degree 4 each
    np.save(tmp_path / "adjacency.npy", np.stack([sparse, sparse, full]))
    np.save(tmp_path / "states.npy",
            np.random.default_rng(0).standard_normal((3, 4, n, 1)).astype(np.float32))
    out = tmp_path / "mine.h5"
    assert invoke("import", "--states", tmp_path / "states.npy", "--adjacency",
                  tmp_path / "adjacency.npy", "--dt", 0.1, "--out", out).exit_code == 0
    by_construction = [0, 1, 3, 1, 0] + [4] * n
    for a in (sparse, full):  # networkx agrees with the construction (A[i, j]: j → i)
        g = nx.from_numpy_array(a.T, create_using=nx.DiGraph)
        assert sorted(d for _, d in g.in_degree()) == sorted(a.sum(axis=1).tolist())
    want = {"min": 0, "median": 3.5, "max": 4}
    assert _expected(np.array(by_construction)) == want
    assert _reported(out) == (want, want)
    assert _shown(out) == ("min 0, median 3.5, max 4",) * 2
    assert "(over every node of the 2 graphs)" in invoke("info", out).output


def test_an_edge_list_above_the_dense_threshold(tmp_path):
    """300 nodes (edge lists only): node i hears i mod 4 others, so a quarter each of the
    nodes have in-degree 0, 1, 2 and 3 and the median lies between 1 and 2."""
    n = 300
    (tmp_path / "edges.txt").write_text("".join(
        f"{(i + s) % n} {i}\n" for i in range(n) for s in range(1, i % 4 + 1)))
    np.save(tmp_path / "states.npy",
            np.random.default_rng(0).standard_normal((2, 3, n, 1)).astype(np.float32))
    out = tmp_path / "ring.h5"
    assert invoke("import", "--states", tmp_path / "states.npy", "--edge-list",
                  tmp_path / "edges.txt", "--directed", "--dt", 0.1, "--out",
                  out).exit_code == 0
    np.testing.assert_array_equal(_networkx_in_degrees(out)[0], np.arange(n) % 4)
    want = {"min": 0, "median": 1.5, "max": 3}
    assert _reported(out) == (want, want)
    assert "(over every node of the graph)" in invoke("info", out).output


def test_a_version_1_file_of_matrices_alone(tmp_path):
    """A hand-written version-1 file (matrices, no edge lists): a ring (in-degree 2 each)
    and a directed path 0 → 1 → 2 → 3 (in-degrees 0, 1, 1, 1)."""
    k, t, n = 4, 3, 4
    ring = np.roll(np.eye(n, dtype=np.uint8), 1, axis=1) | np.roll(np.eye(n, dtype=np.uint8),
                                                                  -1, axis=1)
    path_graph = np.eye(n, k=-1, dtype=np.uint8)  # A[i, i − 1] = 1: node i − 1 sends to i
    path = tmp_path / "v1.h5"
    with h5py.File(path, "w") as f:
        f.attrs.update({"format": "mpnode-dataset", "format_version": 1, "system": "custom",
                        "num_nodes": n, "node_dim": 1, "dt": 0.5,
                        "state_names": json.dumps(["p"])})
        f["time"] = np.arange(t) * 0.5
        f["states"] = np.random.default_rng(0).standard_normal((k, t, n, 1))
        f["graph/adjacency"] = np.stack([ring, path_graph])
        f["graph_index"] = np.array([0, 1, 1, 1], np.int32)
        f["split"] = np.array([0, 0, 1, 2], np.uint8)
    want = {"min": 0, "median": 1.5, "max": 2}
    assert _expected(np.array([2, 2, 2, 2, 0, 1, 1, 1])) == want
    assert _reported(path) == (want, want)


def test_a_file_with_bad_graphs_shows_no_range(tmp_path):
    path = tmp_path / "bad.h5"
    with h5py.File(path, "w") as f:
        f.attrs.update({"format": "mpnode-dataset", "format_version": 1, "system": "custom",
                        "num_nodes": 2, "node_dim": 1, "dt": 0.5,
                        "state_names": json.dumps(["p"])})
        f["time"] = np.arange(3) * 0.5
        f["states"] = np.zeros((1, 3, 2, 1))
        f["graph/adjacency"] = np.full((1, 2, 2), 7, np.uint8)
        f["graph_index"] = np.zeros(1, np.int32)
        f["split"] = np.zeros(1, np.uint8)
    report = json.loads(invoke("check", path, "--json").output)
    assert not report["valid"] and "in_degree" not in report["summary"]
