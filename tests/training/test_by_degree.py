"""`evaluate --by-degree`: the errors by in-degree bin against a computation from the files.

The reference reads the dataset and the `--save-predictions` file with h5py, counts each
node's in-degree from the file's edge list (a bincount of the receivers, so an edge of
multiplicity w counts w times), bins it by its binary exponent, and takes each
node-trajectory's squared errors in numpy.
"""

from __future__ import annotations

import json

import h5py
import numpy as np
import pytest
from conftest import invoke, one_line_error

from mpnode_cli.config.generate import GenerateConfig
from mpnode_cli.config.train import TrainConfig
from mpnode_cli.data.generate import generate
from mpnode_cli.training.by_degree import bin_bounds, degree_bin
from mpnode_cli.training.checkpoint import load_checkpoint
from mpnode_cli.training.loop import train

NODES, MULTIPLICITY = 10, 2


@pytest.fixture(scope="module")
def hub_run(tmp_path_factory):
    """Gene on two 10-node BA graphs with one hub joined to all, by one edge on graph 0 and
    by two parallel edges on graph 1 (in-degree 18 there); a 2-epoch MP-NODE, and a
    2-member ensemble, trained on it."""
    root = tmp_path_factory.mktemp("by_degree")
    data = generate(GenerateConfig(system="gene", nodes=NODES, topology="ba", graphs=2,
                                   hubs=1, hub_multiplicity=MULTIPLICITY, trajectories=24,
                                   t_end=1.0, dt=0.1, out=root / "hub.h5")).path
    runs = {}
    for name, seeds in (("single", 1), ("ensemble", 2)):
        train(TrainConfig(dataset=data, run_dir=root / name, epochs=2, batch_size=8,
                          seeds=seeds, plots=False))
        runs[name] = root / name / "checkpoints" / "best.pt"
    return data, runs


def _evaluate(checkpoint, data, *args) -> dict:
    result = invoke("evaluate", checkpoint, data, "--split", "all", "--by-degree", "--json",
                    *args)
    assert result.exit_code == 0, result.output
    return json.loads(result.output)


def _file_degrees(path) -> tuple[np.ndarray, np.ndarray]:
    """int `[K, N]` each node-trajectory's in-degree from the file's edges, and its bin."""
    with h5py.File(path, "r") as f:
        receivers = f["graph/edges"][1]
        num_edges = f["graph/num_edges"][:]
        graph_index = f["graph_index"][:]
    ends = np.cumsum(num_edges)
    per_graph = np.stack([np.bincount(receivers[end - e:end], minlength=NODES)
                          for e, end in zip(num_edges, ends, strict=True)])  # (G, N)
    degree = per_graph[graph_index]  # (K, N)
    bins = np.array([int(d).bit_length() for d in degree.ravel()]).reshape(degree.shape)
    return degree, bins


def test_bins_match_an_independent_computation(hub_run, tmp_path):
    data, runs = hub_run
    predictions = tmp_path / "pred.h5"
    row = _evaluate(runs["single"], data, "--save-predictions", predictions)
    with h5py.File(data, "r") as f:
        true, split = f["states"][:].astype(np.float64), f["split"][:]  # (K, T, N, D)
    with h5py.File(predictions, "r") as f:
        pred = f["states"][:].astype(np.float64)
    _, bins = _file_degrees(data)
    node_mse = ((pred[:, 1:] - true[:, 1:]) ** 2).mean(axis=(1, 3))  # (K, N)
    mean_t = true[split == 0].mean(axis=(0, 2))  # (T, D): the train split's time mean
    node_tm = ((true[:, 1:] - mean_t[None, 1:, None]) ** 2).mean(axis=(1, 3))
    node_hold = ((true[:, 1:] - true[:, :1]) ** 2).mean(axis=(1, 3))
    lo, hi = np.asarray(load_checkpoint(runs["single"]).dataset["train_range"]["states"]).T
    node_out = ((true < lo) | (true > hi)).any(axis=(1, 3))  # (K, N)

    got = row["by_degree"]
    want_bins = sorted(set(bins.ravel().tolist()))
    assert [(b["lo"], b["hi"]) for b in got] == [bin_bounds(b) for b in want_bins]
    for b, record in zip(want_bins, got, strict=True):
        mask = bins == b
        assert record["node_trajectories"] == int(mask.sum())
        assert record["failed"] == 0
        assert record["mse"] == pytest.approx(node_mse[mask].mean(), rel=1e-4)
        assert record["time_mean"] == pytest.approx(node_tm[mask].mean(), rel=1e-9)
        assert record["hold_x0"] == pytest.approx(node_hold[mask].mean(), rel=1e-9)
        assert record["skill"] == pytest.approx(record["mse"] / record["time_mean"], rel=1e-12)
        assert record["states_outside"] == pytest.approx(node_out[mask].mean(), abs=1e-12)
    assert sum(b["node_trajectories"] for b in got) == true.shape[0] * NODES

    # Weighted by node-trajectories, the bins give evaluate's own overall numbers: the
    # normalized MSE, and the physical one (the mean of the per-state RMSE squared).
    weights = np.array([b["node_trajectories"] for b in got])
    overall = row["result"]
    assert np.dot(weights, [b["mse_normalized"] for b in got]) / weights.sum() == (
        pytest.approx(overall["mse"], rel=1e-6))
    assert np.dot(weights, [b["mse"] for b in got]) / weights.sum() == pytest.approx(
        np.mean(np.square(overall["rmse"])), rel=1e-6)
    assert np.dot(weights, [b["time_mean"] for b in got]) / weights.sum() == pytest.approx(
        node_tm.mean(), rel=1e-9)

    # The table follows evaluate's usual output.
    shown = invoke("evaluate", runs["single"], data, "--by-degree")
    assert shown.exit_code == 0, shown.output
    assert shown.output.index("RMSE") < shown.output.index("by in-degree")
    assert "[16, 32)" in shown.output and "skill" in shown.output


def test_a_multigraph_hub_is_binned_by_its_parallel_edges(hub_run):
    data, runs = hub_run
    with h5py.File(data, "r") as f:
        adjacency, graph_index = f["graph/adjacency"][:], f["graph_index"][:]
    degree, _ = _file_degrees(data)
    assert adjacency.max() == MULTIPLICITY  # a multigraph: parallel edges counted in A
    multi = int(np.flatnonzero(adjacency.reshape(len(adjacency), -1).max(axis=1) > 1)[0])
    senders = (adjacency[multi] > 0).sum(axis=1)  # distinct senders per node
    hub = int(np.argmax(degree[np.flatnonzero(graph_index == multi)[0]]))
    assert senders[hub] == NODES - 1 and adjacency[multi].sum(axis=1)[hub] == 18
    assert degree_bin(np.array([0, 1, 2, 3, 4, 7, 8, 9, 16, 18])).tolist() == [
        0, 1, 2, 2, 3, 3, 4, 4, 5, 5]
    got = {(b["lo"], b["hi"]): b for b in _evaluate(runs["single"], data)["by_degree"]}
    # Only the hub on the multigraph reaches [16, 32), once per trajectory on that graph;
    # counted by distinct senders it would be 9, in [8, 16).
    assert got[(16, 32)]["node_trajectories"] == int((graph_index == multi).sum())


def test_an_ensemble_bins_its_mean_and_its_members(hub_run):
    data, runs = hub_run
    row = _evaluate(runs["ensemble"], data)
    members = [_evaluate(runs["ensemble"], data, "--member", k)["by_degree"] for k in (0, 1)]
    for b, record in enumerate(row["by_degree"]):
        each = np.array([m[b]["mse"] for m in members])
        assert [m[b]["lo"] for m in members] == [record["lo"]] * 2
        assert record["members_mean"] == pytest.approx(each.mean(), rel=1e-5)
        assert record["members_std"] == pytest.approx(each.std(), rel=1e-4, abs=1e-9)
    weights = np.array([b["node_trajectories"] for b in row["by_degree"]])
    assert np.dot(weights, [b["mse_normalized"] for b in row["by_degree"]]) / weights.sum() == (
        pytest.approx(row["result"]["mse"], rel=1e-6))


def test_a_file_of_predictions_is_refused(hub_run, tmp_path):
    data, runs = hub_run
    predictions = tmp_path / "pred.h5"
    saved = invoke("evaluate", runs["single"], data, "--save-predictions", predictions)
    assert saved.exit_code == 0, saved.output
    line = one_line_error(invoke("evaluate", runs["single"], predictions, "--by-degree"))
    assert "predictions, not ground truth" in line
