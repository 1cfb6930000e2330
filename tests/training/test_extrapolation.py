"""The training range a checkpoint records and the extrapolation warning of evaluate,
zeroshot and simulate."""

from __future__ import annotations

import json

import numpy as np
import pytest
from conftest import invoke

from mpnode_cli.config.generate import GenerateConfig
from mpnode_cli.config.train import TrainConfig
from mpnode_cli.data.dataset import TrajectoryData
from mpnode_cli.data.generate import generate
from mpnode_cli.data.stream import StreamedTrajectories
from mpnode_cli.training.checkpoint import load_checkpoint, read_checkpoint, save_checkpoint
from mpnode_cli.training.checkpoint_report import evaluate_checkpoint
from mpnode_cli.training.extrapolation import Extrapolation, data_extrapolation, extrapolation
from mpnode_cli.training.loop import train
from mpnode_cli.training.run import checkpoint_path
from mpnode_cli.training.train_range import TrainRange, training_range


@pytest.fixture(scope="module")
def trained(tmp_path_factory):
    """A 1-epoch MP-NODE on gene over a 4-node chain (in-degrees 1–2), and gene data on a
    complete 6-node graph (in-degree 5)."""
    root = tmp_path_factory.mktemp("extrapolation")
    (root / "chain.txt").write_text("0 1\n1 2\n2 3\n")
    (root / "complete.txt").write_text("".join(f"{i} {j}\n" for i in range(6)
                                               for j in range(i + 1, 6)))
    common = {"system": "gene", "trajectories": 16, "t_end": 0.5, "dt": 0.1}
    chain = generate(GenerateConfig(**common, edge_list=root / "chain.txt",
                                    out=root / "chain.h5")).path
    complete = generate(GenerateConfig(**common, edge_list=root / "complete.txt", seed=3,
                                       out=root / "complete.h5")).path
    train(TrainConfig(dataset=chain, run_dir=root / "run", epochs=1, batch_size=8,
                      plots=False))
    return {"root": root, "chain": chain, "complete": complete,
            "ckpt": checkpoint_path(root / "run", "best")}


def test_the_checkpoint_records_the_train_split_range(trained):
    ckpt = load_checkpoint(trained["ckpt"])
    train_split = TrajectoryData.load(trained["chain"]).subset("train")
    states = train_split.states.numpy()  # [K, T, N, D]
    want = {"in_degree": [1, 2], "num_nodes": [4, 4],
            "states": [[float(states[..., d].min()), float(states[..., d].max())]
                       for d in range(states.shape[-1])]}
    assert ckpt.dataset["train_range"] == want
    assert training_range(train_split).to_dict() == want
    streamed = StreamedTrajectories.open(trained["chain"]).subset("train")
    assert training_range(streamed).to_dict() == want  # read in blocks, the same range
    assert TrainRange.from_dict(want).to_dict() == want
    with pytest.raises(ValueError, match="train_range"):
        TrainRange.from_dict({"in_degree": [1, 2]})


def test_quiet_on_the_training_graphs_and_states(trained):
    ckpt = load_checkpoint(trained["ckpt"])
    data = TrajectoryData.load(trained["chain"])
    row = evaluate_checkpoint(ckpt, data, split="train")
    assert row["extrapolation"] == {
        "in_degree": [1, 2], "train_in_degree": [1, 2], "num_nodes": [4, 4],
        "train_num_nodes": [4, 4], "outside": False, "states_outside_fraction": 0.0,
        "note": None,
        # node by node (tests/training/test_extrapolation_nodes.py): none outside
        "node_states": "true", "trajectory_nodes": 4 * len(data.subset("train")),
        "trajectory_nodes_outside": 0, "nodes_outside": 0, "state_outside": 0,
        "in_degree_outside": 0, "worst": []}
    result = invoke("evaluate", trained["ckpt"], trained["chain"], "--split", "train")
    assert result.exit_code == 0, result.output
    assert "extrapolating" not in result.output


def test_a_higher_in_degree_is_one_line_and_a_json_key(trained):
    result = invoke("zeroshot", trained["ckpt"], trained["complete"])
    assert result.exit_code == 0, result.output
    lines = [line for line in result.output.splitlines() if "extrapolating" in line]
    assert len(lines) == 1
    assert lines[0].startswith("Warning: complete.h5: extrapolating: in-degree 5 here, "
                               "1–2 in training")
    assert "a finetune on such graphs may be needed" in lines[0]

    result = invoke("zeroshot", trained["ckpt"], trained["complete"], "--json")
    assert result.exit_code == 0, result.output
    got = json.loads(result.stdout)["datasets"][0]["extrapolation"]
    assert got["in_degree"] == [5, 5] and got["train_in_degree"] == [1, 2]
    assert got["outside"] is True and got["note"] == lines[0].split(": ", 2)[2]
    # The fraction of state values outside the train range, counted by hand.
    bounds = np.array(load_checkpoint(trained["ckpt"]).dataset["train_range"]["states"])
    states = TrajectoryData.load(trained["complete"]).states.double().numpy()
    outside = (states < bounds[:, 0]) | (states > bounds[:, 1])
    assert got["states_outside_fraction"] == pytest.approx(outside.mean(), rel=1e-12)
    streamed = data_extrapolation(load_checkpoint(trained["ckpt"]),
                                  StreamedTrajectories.open(trained["complete"]))
    assert streamed.to_dict() == got  # read in blocks, the same comparison


def test_simulate_warns_on_a_graph_of_higher_in_degree(trained, tmp_path):
    ckpt = load_checkpoint(trained["ckpt"])
    x0 = TrajectoryData.load(trained["complete"]).states[:2, 0].numpy()  # [2, 6, D]
    np.save(tmp_path / "x0.npy", x0)
    np.save(tmp_path / "a.npy", 1 - np.eye(6, dtype=np.uint8))
    result = invoke("simulate", trained["ckpt"], "--x0", tmp_path / "x0.npy", "--adjacency",
                    tmp_path / "a.npy", "--t-end", 0.3, "--dt", 0.1, "--out",
                    tmp_path / "p.h5", "--json")
    assert result.exit_code == 0, result.output
    got = json.loads(result.stdout)["extrapolation"]
    assert got["in_degree"] == [5, 5] and got["outside"] is True
    assert got["states_outside_fraction"] is None  # no ground truth to compare
    assert got["note"] == "extrapolating: in-degree 5 here, 1–2 in training; a finetune " \
                          "on such graphs may be needed"
    assert ckpt.dataset["train_range"]["in_degree"] == [1, 2]
    result = invoke("simulate", trained["ckpt"], "--x0", tmp_path / "x0.npy", "--adjacency",
                    tmp_path / "a.npy", "--t-end", 0.3, "--dt", 0.1, "--out",
                    tmp_path / "p.h5", "--force")
    assert result.exit_code == 0, result.output
    assert f"Warning: {got['note']}" in result.output.splitlines()


def test_an_old_checkpoint_without_the_record_is_quiet(trained, tmp_path):
    ckpt = load_checkpoint(trained["ckpt"])
    del ckpt.dataset["train_range"]
    old = save_checkpoint(tmp_path / "old.pt", ckpt)
    assert invoke("check", old).exit_code == 0
    data = TrajectoryData.load(trained["complete"])
    assert extrapolation(load_checkpoint(old), data.graphs, data.graph_index.numpy()) is None
    result = invoke("zeroshot", old, trained["complete"])
    assert result.exit_code == 0, result.output
    assert "extrapolating" not in result.output
    result = invoke("zeroshot", old, trained["complete"], "--json")
    assert json.loads(result.stdout)["datasets"][0]["extrapolation"] is None
    # A record that cannot be read is a problem for `check`, hence for every reader
    # (`load_checkpoint` runs the same check), and `extrapolation` gives no note for it.
    ckpt.dataset["train_range"] = {"in_degree": [1]}
    bad = save_checkpoint(tmp_path / "bad.pt", ckpt)
    for verb in ("check", "zeroshot"):
        result = invoke(verb, bad, *([trained["complete"]] if verb == "zeroshot" else []))
        assert result.exit_code == 2 and "train_range must hold" in result.output
    assert extrapolation(read_checkpoint(bad), data.graphs, data.graph_index.numpy()) is None


def test_the_note_names_what_lies_outside():
    inside = {"in_degree": [2, 3], "train_in_degree": [1, 4], "num_nodes": [8, 8],
              "train_num_nodes": [5, 5]}
    # A transferable model may run on another N; its in-degrees are what count.
    assert Extrapolation(**inside, one_size=False, states_outside_fraction=0.0).note is None
    one_size = Extrapolation(**inside, one_size=True, states_outside_fraction=None)
    assert one_size.outside
    assert one_size.note == ("extrapolating: 8 nodes here, 5 in training; a finetune on "
                             "such graphs may be needed")
    # States beyond the train range alone are no note (a test split has some), but they
    # join the note of graphs beyond it.
    states = Extrapolation(**inside, one_size=False, states_outside_fraction=0.0123)
    assert not states.outside and states.note is None
    both = Extrapolation(**inside | {"in_degree": [2, 9]}, one_size=False,
                         states_outside_fraction=0.0123)
    assert both.note == ("extrapolating: in-degree 2–9 here, 1–4 in training; 1.2% of the "
                         "state values outside the training range; a finetune on such graphs "
                         "may be needed")
    tiny = Extrapolation(**inside | {"in_degree": [0, 3]}, one_size=False,
                         states_outside_fraction=1e-6)
    assert "in-degree 0–3 here" in tiny.note and "under 0.1% of the state values" in tiny.note
