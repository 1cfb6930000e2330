"""`mpnode check FILE` and the checks every reader runs first (`data/validate.py`,
`training/checkpoint_check.py`): each way a file can be wrong is one line, exit 2, no traceback."""

from __future__ import annotations

import json
import shutil

import h5py
import numpy as np
import pytest
import torch
from conftest import invoke
from typer.testing import CliRunner

from mpnode_cli.cli.app import app
from mpnode_cli.config.generate import GenerateConfig
from mpnode_cli.data.dataset import TrajectoryData
from mpnode_cli.data.generate import generate
from mpnode_cli.data.validate import check_dataset
from mpnode_cli.training.checkpoint import load_checkpoint, save_checkpoint
from mpnode_cli.training.checkpoint_check import check_checkpoint

runner = CliRunner()
K, T, N = 12, 6, 3  # the tiny lorenz dataset below: 12 trajectories, 6 samples, 3 nodes


@pytest.fixture(scope="module")
def good(tmp_path_factory):
    root = tmp_path_factory.mktemp("check")
    return generate(GenerateConfig(system="lorenz", nodes=N, trajectories=K, t_end=0.25,
                                   dt=0.05, out=root / "good.h5")).path


@pytest.fixture(scope="module")
def ckpt(good, tmp_path_factory):
    run = tmp_path_factory.mktemp("run") / "r"
    result = runner.invoke(app, ["train", str(good), "--epochs", "1", "--batch-size", "8",
                                 "--no-plots", "--run-dir", str(run)])
    assert result.exit_code == 0, result.output
    return run / "checkpoints" / "best.pt"


def errors(result) -> list[str]:
    """The `Error:` lines of a refusal (exit 2), after checking that nothing else broke."""
    assert result.exit_code == 2, result.output
    assert "Traceback" not in result.output
    return [line for line in result.output.splitlines() if line.startswith("Error:")]


def _mutated(good, tmp_path, edit) -> str:
    path = tmp_path / "bad.h5"
    shutil.copy(good, path)
    with h5py.File(path, "r+") as f:
        edit(f)
    return path


def _replace(name, value):
    def edit(f):
        del f[name]
        f[name] = value
    return edit


def _attr(name, value):
    def edit(f):
        f.attrs[name] = value
    return edit


def _nan_at(k, t, n, d):
    def edit(f):
        f["states"][k, t, n, d] = np.nan
    return edit


# Each corruption a user's own file might have, and the words its one line must contain.
CORRUPTIONS = {
    "adjacency of the wrong N": (_replace("graph/adjacency", np.ones((1, N + 1, N + 1),
                                                                    np.uint8)), "[G, N, N]"),
    "graph_index out of range": (_replace("graph_index", np.full(K, 3, np.int32)),
                                 "graph_index points outside"),
    "split of the wrong length": (_replace("split", np.zeros(K - 1, np.uint8)), "split has shape"),
    "split value 5": (_replace("split", np.full(K, 5, np.uint8)), "split must hold 0"),
    "time of the wrong length": (_replace("time", np.arange(T + 2) * 0.05), "time has shape"),
    "missing graph_index": (lambda f: f.__delitem__("graph_index"),
                            "missing dataset 'graph_index'"),
    "missing states": (lambda f: f.__delitem__("states"), "missing dataset 'states'"),
    "state_names not JSON": (_attr("state_names", "x, y, z"), "state_names must be a JSON list"),
    "num_nodes contradicts": (_attr("num_nodes", 5), "num_nodes is 5 but the arrays have 3"),
    "node_dim contradicts": (_attr("node_dim", 2), "node_dim is 2 but the arrays have 3"),
    "dt contradicts time": (_attr("dt", 0.1), "dt is 0.1 but time steps by 0.05"),
    "negative dt": (_attr("dt", -0.05), "dt must be a positive finite number"),
    "NaN in states": (_nan_at(3, 4, 1, 2), "trajectory 3, sample 4, node 1, component 2"),
    "adjacency not 0/1": (_replace("graph/adjacency", np.full((1, N, N), 2, np.uint8)),
                          "only 0 and 1"),
    "edge ids beyond N": (_replace("graph/edges", np.array([[0, 0, 1, 1, 2, 2],
                                                           [1, 2, 0, 2, 0, N]], np.int32)),
                          "must lie in 0..2"),
    "num_edges that do not add up": (_replace("graph/num_edges", np.array([99], np.int64)),
                                     "adds up to 99"),
    "a message twice": (_replace("graph/edges", np.array([[0, 0, 1, 1, 2, 2],
                                                          [1, 1, 0, 2, 1, 0]], np.int32)),
                        "a message twice"),
    "edges and adjacency disagree": (_replace("graph/adjacency", np.zeros((1, N, N), np.uint8)),
                                     "hold different graphs"),
    "missing edges": (lambda f: f.__delitem__("graph/edges"), "missing dataset 'graph/edges'"),
    "another format": (_attr("format", "something-else"), "format 'something-else'"),
    "a newer version": (_attr("format_version", 99), "newer than this mpnode reads"),
    "split of strings": (_replace("split", np.array(["a"] * K, dtype="S1")), "must hold numbers"),
    "system not a string": (_attr("system", np.array([1, 2])), "system must be a non-empty"),
    "lorenz with 2 states": (_replace("states", np.zeros((K, T, N, 2), np.float32)),
                             "name your own data system \"custom\""),
}


def test_a_generated_dataset_is_valid_and_summarized(good):
    result = invoke("check", good)
    assert result.exit_code == 0, result.output
    assert "valid dataset" in result.output and "system: lorenz" in result.output
    report = json.loads(invoke("check", good, "--json").output)
    assert report["valid"] and report["problems"] == []
    facts = report["summary"]
    assert (facts["trajectories"], facts["samples"], facts["num_nodes"], facts["node_dim"]) == (
        K, T, N, 3)
    with h5py.File(good) as f:  # the split counts are the file's
        assert list(facts["split"].values()) == np.bincount(f["split"][()], minlength=3).tolist()


@pytest.mark.parametrize("name", list(CORRUPTIONS))
def test_each_corruption_is_one_line_and_exit_2(good, tmp_path, name):
    edit, words = CORRUPTIONS[name]
    path = _mutated(good, tmp_path, edit)
    lines = errors(invoke("check", path))
    assert any(words in line for line in lines), lines
    report = json.loads(invoke("check", path, "--json").output)
    assert not report["valid"] and any(words in p for p in report["problems"])
    # The readers run the same check first: one line, before any work.
    for verb in (["info"], ["train", "--epochs", "1", "--run-dir", tmp_path / "run"]):
        line = errors(invoke(*verb, path))
        assert len(line) == 1 and "not a valid dataset" in line[0], line
    assert not (tmp_path / "run").exists()


def test_several_problems_give_several_lines(good, tmp_path):
    def edit(f):
        _attr("num_nodes", 9)(f)
        _nan_at(0, 1, 0, 0)(f)
    lines = errors(invoke("check", _mutated(good, tmp_path, edit)))
    assert len(lines) == 2
    line = errors(invoke("train", tmp_path / "bad.h5"))
    assert len(line) == 1 and "(and 1 more: mpnode check" in line[0]


def test_a_hand_written_file_with_only_the_required_fields(tmp_path):
    """What docs/dataset-format.md says a user's own file needs, written with h5py alone:
    no params group, no solver group, no provenance attributes."""
    k, t, n = 6, 5, 4
    ring = np.roll(np.eye(n, dtype=np.uint8), 1, axis=1) | np.roll(np.eye(n, dtype=np.uint8), -1,
                                                                  axis=1)
    path = tmp_path / "mine.h5"
    with h5py.File(path, "w") as f:
        f.attrs.update({"format": "mpnode-dataset", "format_version": 1, "system": "custom",
                        "num_nodes": n, "node_dim": 2, "dt": 0.5,
                        "state_names": json.dumps(["p", "q"])})
        f["time"] = np.arange(t) * 0.5
        f["states"] = np.random.default_rng(0).standard_normal((k, t, n, 2))
        f["graph/adjacency"] = ring[None]
        f["graph_index"] = np.zeros(k, np.int32)
        f["split"] = np.array([0, 0, 0, 0, 1, 2], np.uint8)
    result = invoke("check", path)
    assert result.exit_code == 0, result.output
    data = TrajectoryData.load(path)
    assert data.system == "custom" and tuple(data.states.shape) == (k, t, n, 2)
    assert invoke("info", path).exit_code == 0


def test_a_valid_checkpoint_and_a_run_folder(ckpt):
    report = json.loads(invoke("check", ckpt, "--json").output)
    assert report["valid"] and report["summary"]["model"] == "mpnode"
    assert report["summary"]["epoch"] == 1
    run = ckpt.parent.parent
    result = invoke("check", run)  # a run folder means its best.pt
    assert result.exit_code == 0 and "best.pt" in result.output


def test_checkpoint_problems(ckpt, tmp_path):
    loaded = load_checkpoint(ckpt)
    name = next(iter(loaded.state_dict))
    broken = dict(loaded.state_dict)
    broken[name] = torch.full_like(broken[name], float("nan"))
    loaded.state_dict = broken
    loaded.normalizer = {**loaded.normalizer, "x_std": [1.0, 0.0, 1.0]}
    bad = save_checkpoint(tmp_path / "bad.pt", loaded)
    problems = check_checkpoint(bad).problems
    assert any(f"weight {name} holds" in p for p in problems)
    assert any("x_std must be positive" in p for p in problems)
    assert len(errors(invoke("check", bad))) == len(problems) == 2
    loaded.state_dict = {**broken, name: torch.zeros(2, 2)}
    loaded.normalizer = {**loaded.normalizer, "x_std": [1.0]}
    problems = check_checkpoint(save_checkpoint(tmp_path / "bad2.pt", loaded)).problems
    assert any("shape [2, 2]" in p for p in problems)
    assert any("x_std must hold 3 numbers" in p for p in problems)


def test_files_that_are_neither(good, tmp_path):
    text = tmp_path / "notes.txt"
    text.write_text("hello")
    line = errors(invoke("check", text))[0]
    assert "not an mpnode checkpoint" in line
    # No exception class names in what a user reads.
    assert not any(word in line for word in ("UnpicklingError", "BadZipFile", "RuntimeError"))
    assert "no such file" in errors(invoke("check", tmp_path / "missing.h5"))[0]
    empty = tmp_path / "empty"
    empty.mkdir()
    assert "checkpoints/best.pt" in errors(invoke("check", empty))[0]
    assert check_dataset(text).problems == [f"{text} is not an HDF5 file"]
