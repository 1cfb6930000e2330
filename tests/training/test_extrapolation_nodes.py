"""The per-node extrapolation report: which nodes of which trajectories have states or
in-degrees outside a checkpoint's training range (`node_extrapolation`), the report
`evaluate`, `zeroshot` and `simulate` print and put under `--json`'s "extrapolation", and
simulate's `extrapolation [K, N]` flags."""

from __future__ import annotations

import dataclasses
import json

import h5py
import numpy as np
import pytest
import torch
from conftest import invoke

from mpnode_cli.data.hdf5 import read_dataset
from mpnode_cli.data.hdf5_write import write_dataset
from mpnode_cli.data.stream import StreamedTrajectories
from mpnode_cli.training import extrapolation_nodes
from mpnode_cli.training.checkpoint import load_checkpoint
from mpnode_cli.training.extrapolation import data_extrapolation, node_lines
from mpnode_cli.training.extrapolation_nodes import (
    IN_DEGREE_OUTSIDE,
    PREDICTED_SLACK,
    STATE_OUTSIDE,
    node_extrapolation,
)
from mpnode_cli.training.train_range import TrainRange

NODE_KEYS = {"node_states", "trajectory_nodes", "trajectory_nodes_outside", "nodes_outside",
             "state_outside", "in_degree_outside", "worst"}
WORST_KEYS = {"trajectory", "node", "graph", "in_degree", "in_degree_outside", "how_far",
              "state"}

# Training range of the hand-made cases: in-degrees 1–2; a in [0, 1] (width 1), b in
# [-2, 2] (width 4), c always 5 (width 0: counted in physical units).
TRAIN = TrainRange((1, 2), (3, 3), ((0.0, 1.0), (-2.0, 2.0), (5.0, 5.0)))


def hand_made() -> np.ndarray:
    """`[K=3, T=2, N=3, D=3]` states, every value inside but for:
    trajectory 0 node 2: a = 1.5 at t1 (0.5 widths above);
    trajectory 1 node 0: b = -6 at t0 (1 width below) and a = -0.25 at t1 (0.25 below);
    trajectory 2 node 1: c = 5.125 at t0 (0.125, physical units)."""
    x = np.zeros((3, 2, 3, 3))
    x[..., 0], x[..., 1], x[..., 2] = 0.5, 0.0, 5.0
    x[0, 1, 2, 0] = 1.5
    x[1, 0, 0, 1] = -6.0
    x[1, 1, 0, 0] = -0.25
    x[2, 0, 1, 2] = 5.125
    return x


# Graph 0: in-degrees 1, 2, 2 (inside); graph 1: 0, 2, 3 (nodes 0 and 2 outside).
DEGREE = np.array([[1, 2, 2], [0, 2, 3]])
GRAPH_INDEX = np.array([0, 1, 0])


def test_nodes_how_far_and_flags_by_hand():
    x = hand_made()
    nodes = node_extrapolation(TRAIN, DEGREE, GRAPH_INDEX, [torch.from_numpy(x)],
                               state_names=("a", "b", "c"))
    np.testing.assert_allclose(nodes.how_far, [[0, 0, 0.5], [1.0, 0, 0], [0, 0.125, 0]])
    np.testing.assert_array_equal(nodes.component, [[-1, -1, 0], [1, -1, -1], [-1, 2, -1]])
    np.testing.assert_array_equal(nodes.in_degree, [[1, 2, 2], [0, 2, 3], [1, 2, 2]])
    np.testing.assert_array_equal(nodes.degree_outside, [[0, 0, 0], [1, 0, 1], [0, 0, 0]])
    s, d = STATE_OUTSIDE, IN_DEGREE_OUTSIDE
    assert (s, d) == (1, 2)
    np.testing.assert_array_equal(nodes.flags, [[0, 0, s], [s | d, 0, d], [0, s, 0]])
    assert nodes.flags.dtype == np.uint8
    assert nodes.outside_fraction == pytest.approx(4 / x.size)  # 4 values of 54 outside
    assert nodes.to_dict() == {
        "node_states": "true", "trajectory_nodes": 9, "trajectory_nodes_outside": 4,
        "nodes_outside": 3, "state_outside": 3, "in_degree_outside": 2,
        "worst": [  # by how far, then by how far the in-degree is out
            {"trajectory": 1, "node": 0, "graph": 1, "in_degree": 0,
             "in_degree_outside": True, "how_far": 1.0, "state": "b"},
            {"trajectory": 0, "node": 2, "graph": 0, "in_degree": 2,
             "in_degree_outside": False, "how_far": 0.5, "state": "a"},
            {"trajectory": 2, "node": 1, "graph": 0, "in_degree": 2,
             "in_degree_outside": False, "how_far": 0.125, "state": "c"},
            {"trajectory": 1, "node": 2, "graph": 1, "in_degree": 3,
             "in_degree_outside": True, "how_far": 0.0, "state": None}]}
    assert [node["node"] for node in nodes.to_dict()["worst"]][:2] == [0, 2]
    assert len(nodes.worst(2)) == 2


def test_blocks_chunks_file_rows_and_names(monkeypatch):
    x = hand_made()
    whole = node_extrapolation(TRAIN, DEGREE, GRAPH_INDEX, [torch.from_numpy(x)])
    # Several blocks, each compared a trajectory at a time: the same answer.
    monkeypatch.setattr(extrapolation_nodes, "_BLOCK_VALUES", 1)
    parts = node_extrapolation(TRAIN, DEGREE, GRAPH_INDEX,
                               (torch.from_numpy(x[i:i + 2]) for i in (0, 2)),
                               trajectory=np.array([10, 11, 12]))
    np.testing.assert_array_equal(parts.how_far, whole.how_far)
    np.testing.assert_array_equal(parts.flags, whole.flags)
    worst = parts.to_dict()["worst"]
    assert [w["trajectory"] for w in worst] == [11, 10, 12, 11]  # the rows given
    assert [w["state"] for w in worst] == ["x1", "x0", "x2", None]  # default names


def test_in_degrees_alone_and_predicted_slack():
    alone = node_extrapolation(TRAIN, DEGREE, GRAPH_INDEX)
    assert alone.how_far is None and alone.outside_fraction is None
    np.testing.assert_array_equal(alone.flags, [[0, 0, 0], [2, 0, 2], [0, 0, 0]])
    record = alone.to_dict()
    assert record["node_states"] is None and record["state_outside"] == 0
    assert [(w["node"], w["how_far"]) for w in record["worst"]] == [(0, None), (2, None)]
    # A predicted state a rounding error outside is inside; a true one is not.
    x = hand_made()[:1]
    x[0, 0, 0, 0] = 1.0 + PREDICTED_SLACK / 2
    true = node_extrapolation(TRAIN, DEGREE, [0], [torch.from_numpy(x)])
    predicted = node_extrapolation(TRAIN, DEGREE, [0], [torch.from_numpy(x)],
                                   compared="predicted")
    assert true.flags[0, 0] == STATE_OUTSIDE and predicted.flags[0, 0] == 0
    assert predicted.flags[0, 2] == STATE_OUTSIDE  # 0.5 widths is outside either way
    assert predicted.to_dict()["node_states"] == "predicted"


def test_states_that_do_not_fit_are_refused():
    with pytest.raises(ValueError, match="components"):
        node_extrapolation(TRAIN, DEGREE, GRAPH_INDEX, [torch.zeros(3, 2, 3, 2)])
    with pytest.raises(ValueError, match="trajectories"):
        node_extrapolation(TRAIN, DEGREE, GRAPH_INDEX, [torch.zeros(2, 2, 3, 3)])


def test_the_lines_a_user_reads():
    record = node_extrapolation(TRAIN, DEGREE, GRAPH_INDEX, [torch.from_numpy(hand_made())],
                                state_names=("a", "b", "c")).to_dict()
    record |= {"num_nodes": [3, 3], "train_in_degree": [1, 2]}
    assert node_lines(record) == [
        "3 of 3 nodes outside the training range, in 4 of 9 trajectory·nodes (3 by their "
        "true states, 2 by their in-degree); the worst:",
        "  trajectory 1, node 0: b 1 range widths outside, in-degree 0 (1–2 in training)",
        "  trajectory 0, node 2: a 0.5 range widths outside, in-degree 2",
        "  trajectory 2, node 1: c 0.125 range widths outside, in-degree 2",
        "  trajectory 1, node 2: in-degree 3 (1–2 in training)"]
    inside = node_extrapolation(TRAIN, DEGREE[:1], [0, 0]).to_dict()
    assert node_lines({**inside, "num_nodes": [3, 3]}) == [] and node_lines(None) == []


def expected_flags(states: np.ndarray, bounds: np.ndarray, in_degree: np.ndarray,
                   train_degree, slack: float = 0.0) -> np.ndarray:
    """uint8 `[K, N]` flags recomputed from `states [K, T, N, D]` with numpy."""
    lo, hi = bounds[:, 0], bounds[:, 1]
    width = np.where(hi > lo, hi - lo, 1.0)
    far = (np.maximum(np.maximum(lo - states, states - hi), 0) / width).max(axis=(1, 3))
    degree_out = (in_degree < train_degree[0]) | (in_degree > train_degree[1])
    return ((far > slack) * STATE_OUTSIDE | degree_out * IN_DEGREE_OUTSIDE).astype(np.uint8)


@pytest.fixture(scope="module")
def simulated(tiny_checkpoint, tmp_path_factory):
    """simulate's file and `--json` for 2 trajectories of the tiny 3-node Lorenz model:
    trajectory 0 on the training graph (complete, in-degree 2) with node 1 starting 3
    range widths above x's range; trajectory 1 without the edge 2 → 0 (node 0's
    in-degree 1, outside) with node 2 starting 3 widths below z's range. Every other
    state starts mid-range."""
    root = tmp_path_factory.mktemp("nodes")
    ckpt = load_checkpoint(tiny_checkpoint)
    bounds = np.array(ckpt.dataset["train_range"]["states"])  # (D, 2)
    width = bounds[:, 1] - bounds[:, 0]
    x0 = np.tile(bounds.mean(axis=1), (2, 3, 1))  # (K, N, D)
    x0[0, 1, 0] = bounds[0, 1] + 3 * width[0]
    x0[1, 2, 2] = bounds[2, 0] - 3 * width[2]
    a = np.tile(1 - np.eye(3, dtype=np.uint8), (2, 1, 1))  # a[k, i, j]: j sends to i
    a[1, 0, 2] = 0
    np.save(root / "x0.npy", x0)
    np.save(root / "a.npy", a)
    out = root / "pred.h5"
    args = ("simulate", tiny_checkpoint, "--x0", root / "x0.npy", "--adjacency",
            root / "a.npy", "--t-end", 0.05, "--dt", 0.05, "--dtype", "float64")
    result = invoke(*args, "--out", out, "--json")
    assert result.exit_code == 0, result.output
    human = invoke(*args, "--out", root / "again.h5")
    assert human.exit_code == 0, human.output
    return {"root": root, "out": out, "ckpt": ckpt, "bounds": bounds,
            "json": json.loads(result.stdout)["extrapolation"], "human": human.output,
            "in_degree": a.sum(axis=2)}


def test_simulate_writes_the_flags_of_the_chosen_nodes(simulated):
    with h5py.File(simulated["out"]) as f:
        flags, states = f["extrapolation"][()], f["states"][()]
    assert flags.shape == (2, 3) and flags.dtype == np.uint8
    assert flags[0, 1] & STATE_OUTSIDE and flags[1, 2] & STATE_OUTSIDE
    np.testing.assert_array_equal(flags & IN_DEGREE_OUTSIDE, [[0, 0, 0], [2, 0, 0]])
    train_degree = simulated["ckpt"].dataset["train_range"]["in_degree"]
    assert train_degree == [2, 2]
    np.testing.assert_array_equal(
        flags, expected_flags(states, simulated["bounds"], simulated["in_degree"],
                              train_degree, PREDICTED_SLACK))
    assert read_dataset(simulated["out"]).extrapolation.tolist() == flags.tolist()


def test_simulate_json_and_lines_name_the_worst_nodes(simulated):
    got = simulated["json"]
    assert NODE_KEYS <= set(got) and got["node_states"] == "predicted"
    assert got["states_outside_fraction"] is None  # no ground truth
    assert got["trajectory_nodes"] == 6 and got["in_degree_outside"] == 1
    with h5py.File(simulated["out"]) as f:
        flags = f["extrapolation"][()]
    assert got["trajectory_nodes_outside"] == np.count_nonzero(flags)
    assert got["state_outside"] == np.count_nonzero(flags & STATE_OUTSIDE)
    worst = got["worst"]
    assert all(set(w) == WORST_KEYS for w in worst)
    assert {(w["trajectory"], w["node"]) for w in worst[:2]} == {(0, 1), (1, 2)}
    assert {w["state"] for w in worst[:2]} == {"x", "z"}
    assert all(w["how_far"] >= 2.99 for w in worst[:2])
    assert [w["how_far"] for w in worst] == sorted((w["how_far"] for w in worst),
                                                   reverse=True)
    node0 = [w for w in worst if (w["trajectory"], w["node"]) == (1, 0)]
    assert node0 and node0[0]["in_degree"] == 1 and node0[0]["in_degree_outside"]
    lines = simulated["human"].splitlines()
    head = [i for i, line in enumerate(lines) if "nodes outside the training range" in line]
    assert len(head) == 1
    assert lines[head[0]].endswith("the worst:") and "predicted states" in lines[head[0]]
    listed = lines[head[0] + 1:head[0] + 1 + len(worst)]
    assert all(line.startswith("  trajectory ") for line in listed)
    assert "range widths outside" in listed[0]


def test_evaluate_and_zeroshot_json_carry_the_node_keys(simulated, tiny_checkpoint):
    # The prediction file as data: its states stand as the truth.
    pred = read_dataset(simulated["out"])
    states = pred.states.astype(np.float32).astype(np.float64)  # as evaluate reads them
    want = expected_flags(states, simulated["bounds"], simulated["in_degree"], [2, 2])
    result = invoke("evaluate", tiny_checkpoint, simulated["out"], "--split", "all", "--json")
    assert result.exit_code == 0, result.output
    got = json.loads(result.stdout)["extrapolation"]
    assert NODE_KEYS <= set(got) and got["node_states"] == "true"
    assert got["state_outside"] == np.count_nonzero(want & STATE_OUTSIDE)
    assert got["trajectory_nodes_outside"] == np.count_nonzero(want)
    assert got["nodes_outside"] == np.count_nonzero(want.any(axis=0))
    assert {(w["trajectory"], w["node"]) for w in got["worst"][:2]} == {(0, 1), (1, 2)}
    result = invoke("zeroshot", tiny_checkpoint, simulated["out"], "--json")
    assert result.exit_code == 0, result.output
    assert json.loads(result.stdout)["datasets"][0]["extrapolation"] == got
    result = invoke("zeroshot", tiny_checkpoint, simulated["out"])
    assert result.exit_code == 0, result.output
    assert any(line.startswith("pred.h5: ") and "nodes outside the training range" in line
               for line in result.output.splitlines())


def test_worst_trajectories_are_rows_of_the_file(simulated, tiny_checkpoint):
    # Row 0 in the train split, row 1 in the test split: evaluate's test split reports
    # row 1 (not 0, its index within the split), in memory and streamed alike.
    pred = read_dataset(simulated["out"])
    path = simulated["root"] / "split.h5"
    write_dataset(path, dataclasses.replace(pred, split=np.array([0, 2], np.uint8)))
    result = invoke("evaluate", tiny_checkpoint, path, "--json")
    assert result.exit_code == 0, result.output
    got = json.loads(result.stdout)["extrapolation"]
    assert got["trajectory_nodes"] == 3
    assert got["worst"] and {w["trajectory"] for w in got["worst"]} == {1}
    assert got["worst"][0]["node"] == 2
    streamed = data_extrapolation(simulated["ckpt"],
                                  StreamedTrajectories.open(path).subset("test"))
    assert streamed.to_dict() == got
