"""A float64 run resumes exactly: 1 + 1 epochs give the weights, optimizer moments and
metrics of 2 epochs uninterrupted, to the bit.

Models are built in float32 and cast to the run's dtype. A float64 checkpoint's weights
loaded into the float32 model before the cast would lose their last 29 mantissa bits, and
every later number would move by float32 round-off (about 1e-9 relative). In float32
nothing is rounded, so `tests/training/test_training.py`'s float32 resume test cannot see it.
"""

from __future__ import annotations

import pytest
import torch

from mpnode_cli.config.generate import GenerateConfig
from mpnode_cli.config.train import TrainConfig
from mpnode_cli.data.generate import generate
from mpnode_cli.training.checkpoint import load_checkpoint
from mpnode_cli.training.loop import train
from mpnode_cli.training.run import checkpoint_path, read_metrics


@pytest.fixture(scope="module")
def gene(tmp_path_factory):
    """Gene dynamics on a 2×2 grid: 6 short trajectories (a few batches an epoch)."""
    out = tmp_path_factory.mktemp("data") / "gene.h5"
    generate(GenerateConfig(system="gene", grid=2, trajectories=6, t_end=0.3, dt=0.1,
                            out=out))
    return out


def _config(dataset, run_dir, **kw) -> TrainConfig:
    fields = {"dataset": dataset, "run_dir": run_dir, "dtype": "float64", "batch_size": 2,
              "lr": 1e-2, "epochs": 2, "model_options": {"hidden": 4}, "plots": False}
    return TrainConfig(**(fields | kw))


def _rows(run_dir):
    """Metrics rows without their timings (which differ between identical runs)."""
    return [{k: v for k, v in r.items() if not k.endswith("seconds")}
            for r in read_metrics(run_dir)]


@pytest.mark.parametrize("seeds", [1, 2])
def test_float64_resume_is_bit_identical_to_uninterrupted(gene, tmp_path, seeds):
    whole, resumed = tmp_path / "whole", tmp_path / "resumed"
    train(_config(gene, whole, seeds=seeds))
    train(_config(gene, resumed, seeds=seeds, epochs=1))
    first = load_checkpoint(checkpoint_path(resumed, "last"))
    weights = [v for v in first.state_dict.values() if v.is_floating_point()]
    assert all(v.dtype == torch.float64 for v in weights)
    # Trained weights that float32 cannot hold: a resume that rounds them shows.
    assert any(not torch.equal(v, v.float().double()) for v in weights)
    train(_config(gene, resumed, seeds=seeds), resume=True)

    a = load_checkpoint(checkpoint_path(whole, "last"))
    b = load_checkpoint(checkpoint_path(resumed, "last"))
    assert a.epoch == b.epoch == 2
    assert a.state_dict.keys() == b.state_dict.keys()
    for name, value in a.state_dict.items():
        assert value.dtype == b.state_dict[name].dtype, name
        assert torch.equal(value, b.state_dict[name]), name
    for key, state in a.optimizer["state"].items():
        for name, value in state.items():
            assert torch.equal(value, b.optimizer["state"][key][name]), (key, name)
    assert _rows(whole) == _rows(resumed)


def test_float64_finetune_starts_from_the_parents_exact_weights(gene, tmp_path):
    # The same code path fails the same way for a finetune: its epoch 0 validates the
    # starting weights, on the same data with the parent's normalization.
    train(_config(gene, tmp_path / "parent", epochs=1))
    parent = load_checkpoint(checkpoint_path(tmp_path / "parent", "best"))
    assert parent.epoch == 1  # trained weights, which float32 cannot hold
    train(_config(gene, tmp_path / "child", epochs=1, init_checkpoint=parent.path))
    assert read_metrics(tmp_path / "child")[0]["val_loss"] == parent.metrics["val_loss"]
