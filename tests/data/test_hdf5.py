"""Dataset files (format v3): round trip, atomic writes, and refusal of foreign or newer files."""

from __future__ import annotations

import hashlib
import json

import h5py
import numpy as np
import pytest

from mpnode_cli.data import hdf5_write
from mpnode_cli.data.hdf5 import (
    Dataset,
    DatasetFormatError,
    read_dataset,
    read_header,
)
from mpnode_cli.data.hdf5_write import write_dataset
from mpnode_cli.graphs.matrices import Graphs

K, T, N, D, U, G = 5, 4, 3, 2, 1, 2


def _dataset(**overrides) -> Dataset:
    rng = np.random.default_rng(0)
    fields = dict(
        system="toy",
        dt=0.1,
        state_names=("a", "b"),
        control_names=("u",),
        seed=7,
        config={"system": "toy", "split": [0.6, 0.2, 0.2]},
        time=np.arange(T) * 0.1,
        states=rng.standard_normal((K, T, N, D)).astype(np.float32),
        graphs=Graphs.from_adjacency(
            np.stack([np.ones((N, N), np.uint8) - np.eye(N, dtype=np.uint8)] * G)),
        graph_index=np.array([0, 0, 0, 1, 1], dtype=np.int32),
        split=np.array([0, 0, 0, 1, 2], dtype=np.uint8),
        params={"coupling": rng.standard_normal((G, 3 * N, 3 * N))},
        scalar_params={"sigma": 10.0, "K": 1 / 3},
        solver_status=np.zeros(K, np.int8),
        solver_n_f_evals=np.arange(K, dtype=np.int32),
        controls=rng.standard_normal((K, T, N, U)).astype(np.float32),
        hidden={"load": rng.standard_normal((K, T, 6))},
        extra_attrs={"n_rejected": 3},
    )
    fields.update(overrides)
    return Dataset(**fields)


def _assert_same(a: Dataset, b: Dataset) -> None:
    for name in ("time", "states", "adjacency", "graph_index", "split", "controls"):
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name), err_msg=name)
        assert getattr(a, name).dtype == getattr(b, name).dtype, name
    for name in ("system", "dt", "state_names", "control_names", "seed", "config"):
        assert getattr(a, name) == getattr(b, name), name
    assert a.params.keys() == b.params.keys()
    np.testing.assert_array_equal(a.params["coupling"], b.params["coupling"])
    np.testing.assert_array_equal(a.hidden["load"], b.hidden["load"])
    assert a.scalar_params == b.scalar_params


def test_round_trip(tmp_path):
    ds = _dataset()
    path = write_dataset(tmp_path / "sub" / "d.h5", ds)
    back = read_dataset(path)
    _assert_same(ds, back)
    assert back.extra_attrs == {"n_rejected": 3}
    assert (back.num_trajectories, back.num_nodes, back.node_dim) == (K, N, D)
    assert (back.control_dim, back.num_graphs) == (U, G)
    assert back.mpnode_version and back.created_utc
    np.testing.assert_array_equal(back.solver_n_f_evals, ds.solver_n_f_evals)


def test_layout_matches_format_v3(tmp_path):
    path = write_dataset(tmp_path / "d.h5", _dataset())
    with h5py.File(path) as f:
        assert f.attrs["format"] == "mpnode-dataset" and f.attrs["format_version"] == 3
        assert json.loads(f.attrs["periodic_states"]) == []
        assert (f.attrs["num_nodes"], f.attrs["node_dim"], f.attrs["control_dim"]) == (N, D, U)
        assert json.loads(f.attrs["state_names"]) == ["a", "b"]
        assert json.loads(f.attrs["config"])["system"] == "toy"
        assert f["states"].chunks == (1, T, N, D)  # one trajectory per chunk
        assert f["states"].dtype == np.float32 and f["time"].dtype == np.float64
        assert f["graph/adjacency"].dtype == np.uint8 and f["graph_index"].dtype == np.int32
        assert f["split"].dtype == np.uint8
        assert f["solver/status"].dtype == np.int8 and f["solver/n_f_evals"].dtype == np.int32
        assert f["params/coupling"].shape == (G, 3 * N, 3 * N)
        assert f["params"].attrs["sigma"] == 10.0
        assert f["hidden/load"].shape == (K, T, 6)


def test_no_controls_dataset_when_autonomous(tmp_path):
    ds = _dataset(control_names=(), controls=None, hidden={})
    path = write_dataset(tmp_path / "d.h5", ds)
    with h5py.File(path) as f:
        assert "controls" not in f and "hidden" not in f and f.attrs["control_dim"] == 0
    back = read_dataset(path)
    assert back.controls is None and back.hidden == {}


def test_header_without_data(tmp_path):
    path = write_dataset(tmp_path / "d.h5", _dataset())
    header = read_header(path)
    assert header["shapes"]["states"] == ((K, T, N, D), "float32")
    assert header["attrs"]["state_names"] == ["a", "b"]
    assert header["graphs"].dense().shape == (G, N, N)


def test_refuses_to_overwrite_unless_asked(tmp_path):
    path = write_dataset(tmp_path / "d.h5", _dataset())
    with pytest.raises(FileExistsError, match="--force"):
        write_dataset(path, _dataset(seed=8))
    write_dataset(path, _dataset(seed=8), overwrite=True)
    assert read_dataset(path).seed == 8


@pytest.mark.parametrize("error", [KeyboardInterrupt, RuntimeError])
def test_interrupted_write_leaves_nothing(tmp_path, monkeypatch, error):
    real_write = hdf5_write._write

    def write_then_fail(f, ds, *check):
        real_write(f, ds, *check)  # a fully written temp file, then the interruption
        raise error("interrupted")

    monkeypatch.setattr(hdf5_write, "_write", write_then_fail)
    with pytest.raises(error):
        write_dataset(tmp_path / "d.h5", _dataset())
    assert list(tmp_path.iterdir()) == []


def test_interrupted_overwrite_keeps_the_old_file(tmp_path, monkeypatch):
    path = write_dataset(tmp_path / "d.h5", _dataset(seed=1))

    def fail(f, ds, *check):
        raise KeyboardInterrupt

    monkeypatch.setattr(hdf5_write, "_write", fail)
    with pytest.raises(KeyboardInterrupt):
        write_dataset(path, _dataset(seed=2), overwrite=True)
    assert read_dataset(path).seed == 1
    assert [p.name for p in tmp_path.iterdir()] == ["d.h5"]


def test_newer_version_is_rejected(tmp_path):
    path = write_dataset(tmp_path / "d.h5", _dataset())
    with h5py.File(path, "a") as f:
        f.attrs["format_version"] = 5
    with pytest.raises(DatasetFormatError, match=r"version 5, newer.*upgrade mpnode"):
        read_dataset(path)
    with pytest.raises(DatasetFormatError, match="newer"):
        read_header(path)


def test_other_files_are_rejected(tmp_path):
    foreign = tmp_path / "foreign.h5"
    with h5py.File(foreign, "w") as f:
        f.attrs["format"] = "something-else"
    with pytest.raises(DatasetFormatError, match=r"not an mpnode dataset.*something-else"):
        read_dataset(foreign)
    bare = tmp_path / "bare.h5"
    h5py.File(bare, "w").close()
    with pytest.raises(DatasetFormatError, match="no 'format' attribute"):
        read_dataset(bare)
    text = tmp_path / "text.h5"
    text.write_text("not hdf5")
    with pytest.raises(DatasetFormatError, match="not an HDF5 file"):
        read_dataset(text)
    with pytest.raises(FileNotFoundError):
        read_dataset(tmp_path / "missing.h5")


def test_inconsistent_shapes_are_refused(tmp_path):
    with pytest.raises(ValueError, match="graph_index has shape"):
        write_dataset(tmp_path / "d.h5", _dataset(graph_index=np.zeros(K + 1, np.int32)))
    with pytest.raises(ValueError, match="outside the graphs"):
        write_dataset(tmp_path / "d.h5", _dataset(graph_index=np.full(K, G, np.int32)))
    with pytest.raises(ValueError, match="would overwrite a format attribute"):
        write_dataset(tmp_path / "d.h5", _dataset(extra_attrs={"seed": 1}))
    assert list(tmp_path.iterdir()) == []


# ----- graphs: edge lists for every file, matrices up to DENSE_GRAPH_MAX_NODES ----------------


def _small_world(n: int, seed: int) -> np.ndarray:
    """A directed random graph [N, N] uint8 written entry by entry (zero diagonal)."""
    a = (np.random.default_rng(seed).random((n, n)) < 3 / n).astype(np.uint8)
    np.fill_diagonal(a, 0)
    return a


def test_small_graphs_round_trip_as_edges_and_matrices(tmp_path):
    mats = np.stack([_small_world(N, 1), _small_world(N, 2)])
    path = write_dataset(tmp_path / "d.h5", _dataset(graphs=Graphs.from_adjacency(mats)))
    with h5py.File(path) as f:
        np.testing.assert_array_equal(f["graph/adjacency"][()], mats)
        edges, counts = f["graph/edges"][()], f["graph/num_edges"][()]
    # The edges written are the matrices' nonzero entries, graph after graph.
    for g, (start, stop) in enumerate(zip(np.cumsum(counts) - counts, np.cumsum(counts),
                                          strict=True)):
        receivers, senders = np.nonzero(mats[g])
        np.testing.assert_array_equal(edges[0, start:stop], senders)
        np.testing.assert_array_equal(edges[1, start:stop], receivers)
    back = read_dataset(path)
    np.testing.assert_array_equal(back.adjacency, mats)


def test_large_graphs_round_trip_as_edges_only(tmp_path):
    from mpnode_cli.graphs.matrices import DENSE_GRAPH_MAX_NODES, EdgeList

    n = DENSE_GRAPH_MAX_NODES + 44
    rng = np.random.default_rng(3)
    lists = []
    for _ in range(G):
        s, r = rng.integers(0, n, 900), rng.integers(0, n, 900)
        lists.append(EdgeList.build(n, s[s != r], r[s != r]))
    graphs = Graphs.from_edge_lists(n, lists)
    ds = _dataset(states=np.zeros((K, T, n, D), np.float32), controls=None, control_names=(),
                  graphs=graphs)
    path = write_dataset(tmp_path / "d.h5", ds)
    with h5py.File(path) as f:
        assert "graph/adjacency" not in f
        assert f["graph/edges"].dtype == np.int32 and f["graph/edges"].shape == (
            2, graphs.num_edges.sum())
    back = read_dataset(path).graphs
    for g in range(G):
        pairs = set(zip(lists[g].senders.tolist(), lists[g].receivers.tolist(), strict=True))
        got = back.edges(g)
        assert set(zip(got.senders.tolist(), got.receivers.tolist(), strict=True)) == pairs
        assert len(got) == len(pairs)


def _write_v1(path, adjacency: np.ndarray, states: np.ndarray) -> None:
    """A version-1 file, as mpnode wrote them before edge lists: the matrices only."""
    k, t, n, d = states.shape
    with h5py.File(path, "w") as f:
        f.attrs.update({"format": "mpnode-dataset", "format_version": 1, "system": "custom",
                        "num_nodes": n, "node_dim": d, "dt": 0.1,
                        "state_names": json.dumps([f"x{i}" for i in range(d)])})
        f["time"] = np.arange(t) * 0.1
        f["states"] = states
        f["graph/adjacency"] = adjacency
        f["graph_index"] = np.arange(k, dtype=np.int32) % len(adjacency)
        f["split"] = np.array([0, 0, 1, 2][:k] + [0] * max(0, k - 4), np.uint8)


@pytest.mark.parametrize("n", [6, 300], ids=["small", "large"])
def test_version_1_files_read_with_their_edges(tmp_path, n):
    from mpnode_cli.data.dataset import TrajectoryData
    from mpnode_cli.data.validate import check_dataset

    mats = np.stack([_small_world(n, 5), _small_world(n, 6)]).astype(np.float32)  # any dtype
    states = np.random.default_rng(0).standard_normal((4, T, n, 1)).astype(np.float32)
    path = tmp_path / "v1.h5"
    _write_v1(path, mats, states)
    assert check_dataset(path).ok, check_dataset(path).problems
    ds = read_dataset(path)
    for g in range(2):
        receivers, senders = np.nonzero(mats[g])
        np.testing.assert_array_equal(ds.graphs.edges(g).senders, senders)
        np.testing.assert_array_equal(ds.graphs.edges(g).receivers, receivers)
    # The fingerprint, written out from its definition: float32 states, the graphs (the
    # matrices as stored up to 256 nodes, the edge lists above), graph_index, time.
    def expected(graph_bytes: bytes) -> str:
        tail = np.array([0, 1, 0, 1], np.int32).tobytes() + (np.arange(T) * 0.1).tobytes()
        return hashlib.sha256(states.tobytes() + graph_bytes + tail).hexdigest()

    if n <= 256:
        np.testing.assert_array_equal(ds.adjacency, mats)
        as_read, as_written = mats.tobytes(), mats.astype(np.uint8).tobytes()
    else:
        senders = np.concatenate([np.nonzero(m)[1] for m in mats]).astype(np.int64)
        receivers = np.concatenate([np.nonzero(m)[0] for m in mats]).astype(np.int64)
        counts = np.array([np.count_nonzero(m) for m in mats], np.int64)
        as_read = as_written = senders.tobytes() + receivers.tobytes() + counts.tobytes()
    assert TrajectoryData.load(path).fingerprint == expected(as_read)
    # Written again, it is a version-3 file of the same data (matrices now stored as uint8).
    again = write_dataset(tmp_path / "v2.h5", ds)
    with h5py.File(again) as f:
        assert f.attrs["format_version"] == 3 and ("graph/adjacency" in f) == (n <= 256)
    assert TrajectoryData.load(again).fingerprint == expected(as_written)
