"""End to end above `DENSE_GRAPH_MAX_NODES`: generate Kuramoto on 300 nodes (edge lists
only in the file), check and summarize it, train one epoch, evaluate with saved
predictions, and simulate on the same graph from an edge-list file; the model's rollout
from edges is compared with a rollout from the `[N, N]` matrix built here."""

from __future__ import annotations

import json

import h5py
import numpy as np
import pytest
import torch
from conftest import invoke

from mpnode_cli.data.hdf5 import read_dataset
from mpnode_cli.graphs.matrices import DENSE_GRAPH_MAX_NODES
from mpnode_cli.graphs.topologies import make_graph

N = 300


@pytest.fixture(scope="module")
def trained(tmp_path_factory):
    assert N > DENSE_GRAPH_MAX_NODES
    root = tmp_path_factory.mktemp("sparse")
    data = root / "k.h5"
    result = invoke("generate", "kuramoto", "--nodes", N, "--trajectories", 6, "--t-end", 0.3,
                    "--dt", 0.1, "--seed", 1, "--out", data)
    assert result.exit_code == 0, result.output
    # Long runs compile the solver's step ("auto"); one epoch here is not worth compiling.
    config = root / "train.toml"
    config.write_text("[solver]\ncompile = false\n")
    run = root / "run"
    result = invoke("train", data, "--config", config, "--epochs", 1, "--batch-size", 2,
                    "--no-plots", "--run-dir", run)
    assert result.exit_code == 0, result.output
    return {"root": root, "data": data, "run": run}


def test_the_file_holds_edges_and_reads_everywhere(trained):
    data = trained["data"]
    with h5py.File(data) as f:
        assert "graph/adjacency" not in f
        assert f.attrs["format_version"] == 3
        edges, counts = f["graph/edges"][()], f["graph/num_edges"][()]
    a = make_graph("ba", N, seed=0, m=5)  # the default graph seed's BA graph, m = 5
    assert counts.tolist() == [int(a.sum())]
    rebuilt = np.zeros((N, N), np.uint8)
    rebuilt[edges[1], edges[0]] = 1
    np.testing.assert_array_equal(rebuilt, a)
    report = json.loads(invoke("check", data, "--json").output)
    assert report["valid"] and report["summary"]["edges"] == int(a.sum())
    info = json.loads(invoke("info", data, "--json").output)
    assert info["num_nodes"] == N and not info["directed"]
    assert info["edges_mean"] == a.sum() / 2


def test_one_epoch_trained_and_evaluated(trained, tmp_path):
    summary = json.loads((trained["run"] / "summary.json").read_text())
    assert summary["epochs"] == 1 and summary["num_nodes"] == N
    assert np.isfinite(summary["min_val_loss"])
    out = tmp_path / "pred.h5"
    result = invoke("evaluate", trained["run"], trained["data"], "--split", "all",
                    "--save-predictions", out)
    assert result.exit_code == 0, result.output
    assert invoke("check", out).exit_code == 0
    with h5py.File(out) as f:
        assert "graph/adjacency" not in f


def test_simulate_from_edges_equals_a_rollout_from_the_matrix(trained, tmp_path):
    from mpnode_cli.training.checkpoint import load_checkpoint
    from mpnode_cli.training.predict import rollout_solver

    a = make_graph("ba", N, seed=0, m=5)
    receivers, senders = np.nonzero(np.triu(a))
    (tmp_path / "g.txt").write_text("".join(f"{i} {j}\n" for i, j in zip(senders, receivers,
                                                                         strict=True)))
    x0 = read_dataset(trained["data"]).states[:2, 0].astype(np.float64)  # [2, N, 3]
    np.save(tmp_path / "x0.npy", x0)
    out = tmp_path / "sim.h5"
    result = invoke("simulate", trained["run"], "--x0", tmp_path / "x0.npy", "--edge-list",
                    tmp_path / "g.txt", "--t-end", 0.3, "--dt", 0.1, "--out", out)
    assert result.exit_code == 0, result.output
    predicted = read_dataset(out).states

    ckpt = load_checkpoint(trained["run"] / "checkpoints" / "best.pt")
    model, norm = ckpt.build_model(), ckpt.build_normalizer()
    with torch.no_grad():
        x = norm.norm_x(torch.from_numpy(x0).float())
        dense = torch.from_numpy(a).float().expand(2, N, N)  # the matrix, at this size fine
        roll = model.rollout(x, torch.tensor([0.0, 0.1, 0.2, 0.3], dtype=torch.float64),
                             dense, solver=rollout_solver(ckpt))
    np.testing.assert_allclose(predicted, norm.denorm_x(roll.states).numpy(), rtol=1e-4,
                               atol=1e-5)


def test_big_graph_rollouts_are_batched_by_edges_with_the_same_errors(trained, monkeypatch):
    from mpnode_cli.data.dataset import TrajectoryData
    from mpnode_cli.graphs import matrices as graphs_module
    from mpnode_cli.training import evaluate as ev
    from mpnode_cli.training.checkpoint import load_checkpoint

    ckpt = load_checkpoint(trained["run"] / "checkpoints" / "best.pt")
    model, normalizer = ckpt.build_model(), ckpt.build_normalizer()
    data = TrajectoryData.load(trained["data"])
    edges = int(data.graphs.num_edges.max())
    whole = ev.evaluate(model, data, normalizer, batch_size=1024)  # 6 trajectories ≤ cap
    sizes = []
    rollout = type(model).rollout_from_data

    def spy(self, x, *args, **kwargs):
        sizes.append(x.shape[0])
        return rollout(self, x, *args, **kwargs)

    monkeypatch.setattr(type(model), "rollout_from_data", spy)
    monkeypatch.setattr(graphs_module, "EDGE_ROWS", 2 * edges + 1)  # two per batch
    capped = ev.evaluate(model, data, normalizer, batch_size=1024)
    assert sizes == [2, 2, 2]
    assert capped.mse == pytest.approx(whole.mse, rel=1e-6)
    assert capped.trajectories == whole.trajectories == 6
