"""A bad checkpoint is one `Error:` line naming the file and what is wrong, exit 2, in every
verb that reads one: the check `mpnode check` runs (`checkpoint_problems`) is the one
`load_checkpoint` runs for evaluate, zeroshot, finetune, simulate and train --resume.

The defects as a user met them: a weight of the wrong shape gave a `RuntimeError`
traceback in evaluate, zeroshot, finetune and simulate; NaN weights let evaluate exit 0
with every rollout failed; `check` caught both.
"""

from __future__ import annotations

import shutil

import numpy as np
import pytest
import torch
from conftest import invoke, one_line_error

from mpnode_cli.config.generate import GenerateConfig
from mpnode_cli.data.generate import generate
from mpnode_cli.training.checkpoint import load_checkpoint, save_checkpoint

FAST = ["--batch-size", "8", "--no-plots"]


@pytest.fixture(scope="module")
def trained(tmp_path_factory):
    """A tiny lorenz dataset (N = 3) and a 1-epoch MP-NODE run on it."""
    root = tmp_path_factory.mktemp("ckpt")
    data = generate(GenerateConfig(system="lorenz", nodes=3, trajectories=12, t_end=0.25,
                                   dt=0.05, out=root / "l3.h5")).path
    run = root / "run"
    result = invoke("train", data, "--epochs", 1, "--run-dir", run, *FAST)
    assert result.exit_code == 0, result.output
    return {"data": data, "run": run}


def first_weight(ckpt) -> str:
    return next(name for name, value in ckpt.state_dict.items() if value.dim() == 2)


def wrong_shape(ckpt):
    name = first_weight(ckpt)
    ckpt.state_dict = {**ckpt.state_dict, name: torch.zeros(2, 2)}
    return "shape [2, 2]"


def nan_weights(ckpt):
    ckpt.state_dict = {k: torch.full_like(v, float("nan")) if v.is_floating_point() else v
                       for k, v in ckpt.state_dict.items()}
    return "non-finite values"


def zero_std(ckpt):
    ckpt.normalizer = {**ckpt.normalizer, "x_std": [1.0, 0.0, 1.0]}
    return "x_std must be positive"


def tiny_std(ckpt):  # positive as a Python float, zero in the float32 it is applied in
    ckpt.normalizer = {**ckpt.normalizer, "x_std": [1e-300, 1.0, 1.0]}
    return "x_std must be positive"


def missing_weight(ckpt):
    name = first_weight(ckpt)
    ckpt.state_dict = {k: v for k, v in ckpt.state_dict.items() if k != name}
    return "lacks weights"


def other_config(ckpt):  # weights of one architecture, the config of another
    ckpt.model_config = {**ckpt.model_config, "hidden": 2 * ckpt.model_config["hidden"]}
    return "the model expects"


def complex_weight(ckpt):
    name = first_weight(ckpt)
    ckpt.state_dict = {**ckpt.state_dict, name: ckpt.state_dict[name].to(torch.complex64)}
    return "not a dense real tensor"


def short_range(ckpt):  # the extrapolation note would compare 2 ranges with 3 states
    ckpt.dataset = {**ckpt.dataset, "train_range": {
        **ckpt.dataset["train_range"], "states": ckpt.dataset["train_range"]["states"][:2]}}
    return "train_range holds 2 state ranges"


CORRUPTIONS = {f.__name__: f for f in (wrong_shape, nan_weights, zero_std, tiny_std,
                                       missing_weight, other_config, complex_weight,
                                       short_range)}


def corrupted(trained, tmp_path, name: str):
    """`best.pt` of the run, edited; the problem text a refusal must contain."""
    ckpt = load_checkpoint(trained["run"])
    expected = CORRUPTIONS[name](ckpt)
    return save_checkpoint(tmp_path / f"{name}.pt", ckpt), expected


def simulate_args(tmp_path):
    np.save(tmp_path / "x0.npy", np.zeros((2, 3, 3)))
    np.save(tmp_path / "a.npy", np.ones((3, 3)) - np.eye(3))
    return ["--x0", tmp_path / "x0.npy", "--adjacency", tmp_path / "a.npy", "--t-end", 0.1,
            "--dt", 0.05, "--out", tmp_path / "sim.h5"]


@pytest.mark.parametrize("verb", ["evaluate", "zeroshot", "finetune", "simulate"])
@pytest.mark.parametrize("name", ["wrong_shape", "nan_weights"])
def test_every_reader_refuses_a_bad_checkpoint_in_one_line(trained, tmp_path, verb, name):
    bad, expected = corrupted(trained, tmp_path, name)
    args = {"evaluate": [trained["data"]], "zeroshot": [trained["data"]],
            "finetune": [trained["data"], "--epochs", 1, "--run-dir", tmp_path / "ft", *FAST],
            "simulate": simulate_args(tmp_path)}[verb]
    line = one_line_error(invoke(verb, bad, *args))
    assert str(bad) in line and expected in line
    assert not (tmp_path / "ft").exists() and not (tmp_path / "sim.h5").exists()


@pytest.mark.parametrize("name", list(CORRUPTIONS))
def test_evaluate_says_what_check_says(trained, tmp_path, name):
    """The same check: check finds the problem, and evaluate's one line is check's first."""
    bad, expected = corrupted(trained, tmp_path, name)
    checked = invoke("check", bad)
    assert checked.exit_code == 2 and expected in checked.output, checked.output
    first = checked.output.splitlines()[0].removeprefix(f"Error: {bad}: ")
    line = one_line_error(invoke("evaluate", bad, trained["data"]))
    assert first in line


def resumable(trained, tmp_path, edit):
    """A copy of the run whose `last.pt` was edited (`edit(ckpt)`)."""
    run = tmp_path / "run"
    shutil.copytree(trained["run"], run)
    last = run / "checkpoints" / "last.pt"
    ckpt = load_checkpoint(last)
    edit(ckpt)
    save_checkpoint(last, ckpt)
    return run


@pytest.mark.parametrize("what", ["weights", "optimizer", "rng"])
def test_resume_refuses_a_bad_last_checkpoint(trained, tmp_path, what):
    def edit(ckpt):
        if what == "weights":
            wrong_shape(ckpt)
        elif what == "optimizer":
            state = ckpt.optimizer["state"]
            index = next(iter(state))
            state[index] = {**state[index], "exp_avg": torch.zeros(7)}
        else:
            ckpt.rng = {**ckpt.rng, "torch": torch.zeros(3, dtype=torch.uint8)}

    run = resumable(trained, tmp_path, edit)
    line = one_line_error(invoke("train", "--resume", run, "--epochs", 2))
    assert "last.pt" in line and {"weights": "shape", "optimizer": "exp_avg",
                                  "rng": "RNG state"}[what] in line
    result = invoke("check", run / "checkpoints" / "last.pt")
    assert result.exit_code == 2
