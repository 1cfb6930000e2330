"""Naive baselines beside every error: `baseline_mse` against a hand computation in numpy,
and the train split it takes its time mean from."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
import torch

from mpnode_cli.config import GenerateConfig, TrainConfig
from mpnode_cli.data.dataset import Normalizer, TrajectoryData
from mpnode_cli.data.generate import generate
from mpnode_cli.graphs import Graphs
from mpnode_cli.training.checkpoint import load_checkpoint
from mpnode_cli.training.evaluate import baseline_mse, evaluate_checkpoint, train_reference
from mpnode_cli.training.loop import train
from mpnode_cli.training.run import checkpoint_path


def synthetic(k: int, t: int, seed: int, dt: float = 0.1) -> TrajectoryData:
    """K random trajectories of 3 nodes × 2 features on a complete graph, all "train"."""
    rng = np.random.default_rng(seed)
    states = rng.normal(size=(k, t, 3, 2)).cumsum(axis=1) * [1.0, 5.0] + [0.0, 2.0]
    return TrajectoryData(
        states=torch.tensor(states, dtype=torch.float32), controls=None,
        graphs=Graphs.from_adjacency(np.ones((1, 3, 3), np.uint8)),
        graph_index=torch.zeros(k, dtype=torch.long),
        time=torch.arange(t, dtype=torch.float64) * dt,
        split=torch.zeros(k, dtype=torch.uint8), system="toy", state_names=("a", "b"),
        control_names=(), path=Path(f"toy{seed}.h5"), fingerprint=str(seed))


def by_hand(train_states: np.ndarray, x: np.ndarray, mean: np.ndarray, std: np.ndarray,
            train_t: int) -> tuple[float, float]:
    """Both baselines with explicit loops over trajectories, times and nodes."""
    z = (x - mean) / std
    z_train = (train_states - mean) / std
    hold, tmean, count = 0.0, 0.0, 0
    for k in range(z.shape[0]):
        for t in range(1, z.shape[1]):
            # the train mean at t, or at the last train time beyond the train horizon
            s = min(t, train_t - 1)
            avg = z_train[:, s].reshape(-1, z.shape[3]).mean(axis=0)
            for n in range(z.shape[2]):
                hold += float(((z[k, t, n] - z[k, 0, n]) ** 2).sum())
                tmean += float(((z[k, t, n] - avg) ** 2).sum())
                count += z.shape[3]
    return hold / count, tmean / count


def test_baselines_match_a_hand_computation():
    train_set, test_set = synthetic(6, 5, seed=1), synthetic(4, 5, seed=2)
    norm = Normalizer.fit(train_set.states)
    got = baseline_mse(train_set, test_set, norm)
    mean, std = norm.x_mean.double().numpy(), norm.x_std.double().numpy()
    hold, tmean = by_hand(train_set.states.double().numpy(), test_set.states.double().numpy(),
                          mean, std, train_t=5)
    assert got["hold_x0"] == pytest.approx(hold, rel=1e-9)
    assert got["time_mean"] == pytest.approx(tmean, rel=1e-9)


def test_a_longer_horizon_holds_the_last_train_mean():
    train_set, longer = synthetic(6, 5, seed=1), synthetic(4, 9, seed=3)
    norm = Normalizer.fit(train_set.states)
    got = baseline_mse(train_set, longer, norm)
    hold, tmean = by_hand(train_set.states.double().numpy(), longer.states.double().numpy(),
                          norm.x_mean.double().numpy(), norm.x_std.double().numpy(), train_t=5)
    assert got == pytest.approx({"hold_x0": hold, "time_mean": tmean}, rel=1e-9)
    # A shorter horizon uses the overlapping times only.
    shorter = synthetic(4, 3, seed=4)
    _, tmean = by_hand(train_set.states.double().numpy(), shorter.states.double().numpy(),
                       norm.x_mean.double().numpy(), norm.x_std.double().numpy(), train_t=5)
    assert baseline_mse(train_set, shorter, norm)["time_mean"] == pytest.approx(tmean, rel=1e-9)


def test_empty_data_gives_nan():
    train_set = synthetic(3, 4, seed=1)
    norm = Normalizer.fit(train_set.states)
    empty = train_set.take(torch.zeros(3, dtype=torch.bool))
    assert all(math.isnan(v) for v in baseline_mse(train_set, empty, norm).values())
    got = baseline_mse(empty, train_set, norm)
    assert math.isfinite(got["hold_x0"]) and math.isnan(got["time_mean"])


@pytest.fixture(scope="module")
def run(tmp_path_factory):
    """A 1-epoch MP-NODE on gene 2×2 trained on its first 10 train trajectories."""
    root = tmp_path_factory.mktemp("baselines")
    data = generate(GenerateConfig(system="gene", grid=2, trajectories=30, t_end=1.0, dt=0.1,
                                   out=root / "gene.h5")).path
    train(TrainConfig(dataset=data, run_dir=root / "run", epochs=1, batch_size=8,
                      trajectories=10, plots=False))
    return data, root / "run"


def test_summary_and_evaluation_carry_the_training_split_baselines(run, tmp_path):
    data_path, run_dir = run
    data = TrajectoryData.load(data_path)
    ckpt = load_checkpoint(checkpoint_path(run_dir, "best"))
    train_set, note = train_reference(ckpt, data)
    assert len(train_set) == 10 and note == "the train split of gene.h5"  # the split training used
    expected = baseline_mse(train_set, data.subset("test"), ckpt.build_normalizer())
    summary = json.loads((run_dir / "summary.json").read_text())
    assert summary["baselines"] == pytest.approx(expected, rel=1e-9)
    row = evaluate_checkpoint(ckpt, data, split="test")
    assert row["baselines"] == pytest.approx(expected, rel=1e-9)

    # Without the training file, the evaluated dataset's own train split stands in.
    other = generate(GenerateConfig(system="gene", grid=2, trajectories=20, t_end=1.0, dt=0.1,
                                    seed=5, out=tmp_path / "other.h5")).path
    moved = TrajectoryData.load(other)
    ckpt.dataset = {**ckpt.dataset, "path": str(tmp_path / "gone.h5")}
    train_set, note = train_reference(ckpt, moved)
    assert len(train_set) == len(moved.subset("train")) and "missing or changed" in note
