"""Naive baselines beside every error: `baseline_mse` against a hand computation in numpy,
and the train split it takes its time mean from."""

from __future__ import annotations

import json
import math
from dataclasses import replace

import numpy as np
import pytest
import torch
from conftest import synthetic

from mpnode_cli.config.generate import GenerateConfig
from mpnode_cli.config.train import TrainConfig
from mpnode_cli.data.dataset import Normalizer, TrajectoryData
from mpnode_cli.data.generate import generate
from mpnode_cli.models.registry import build_model
from mpnode_cli.solver.options import SolverOptions
from mpnode_cli.training.checkpoint import load_checkpoint
from mpnode_cli.training.checkpoint_report import evaluate_checkpoint, train_reference
from mpnode_cli.training.eval_result import pooled
from mpnode_cli.training.evaluate import baseline_mse, evaluate
from mpnode_cli.training.loop import train
from mpnode_cli.training.run import checkpoint_path


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


def test_pooled_time_mean_of_several_train_splits():
    """Train splits of 3 and 4 nodes and 5 and 7 samples: at each time, the mean over the
    trajectories and nodes of those that have that sample."""
    a, b = synthetic(6, 5, seed=1), synthetic(4, 7, seed=5, nodes=4)
    norm = Normalizer.fit([a.states, b.states])
    scored = synthetic(3, 7, seed=6)
    z = [norm.norm_x(d.states.double()).numpy() for d in (a, b)]
    mean = np.stack([  # (T, D) by hand
        (sum(part[:, t].sum(axis=(0, 1)) for part in z if part.shape[1] > t)
         / sum(part.shape[0] * part.shape[2] for part in z if part.shape[1] > t))
        for t in range(7)])
    x = norm.norm_x(scored.states.double()).numpy()
    want = ((x[:, 1:] - mean[None, 1:, None, :]) ** 2).mean()
    assert baseline_mse([a, b], scored, norm)["time_mean"] == pytest.approx(want, rel=1e-9)
    # Splits of one size pool as their concatenation does.
    c = synthetic(2, 5, seed=7)
    both = a.take(torch.arange(6))
    both = replace(both, states=torch.cat([a.states, c.states]))
    assert baseline_mse([a, c], scored, norm) == pytest.approx(
        baseline_mse(both, scored, norm), rel=1e-12)


def test_pooled_errors_are_those_of_the_datasets_taken_as_one(float64_default):
    """`pooled` of two parts of a split equals `evaluate` of the whole split (independent:
    the whole is evaluated in one pass); parts of other N weigh by their values."""
    data = synthetic(7, 6, seed=2)
    norm = Normalizer.fit(data.states)
    torch.manual_seed(0)
    model = build_model("mpnode", {"node_dim": 2, "hidden": 8})
    solver = SolverOptions(fixed_dt=0.05)
    parts = [data.take(torch.arange(4)), data.take(torch.arange(4, 7))]
    each = [evaluate(model, part, norm, solver=solver) for part in parts]
    whole = evaluate(model, data, norm, solver=solver).to_dict()
    got = pooled(each, [3, 3]).to_dict()
    for key in ("trajectories", "failed"):
        assert got[key] == whole[key], key
    assert got["n_f_evals"] == sum(r.n_f_evals for r in each)  # two passes, each counted
    # In float64 (`float64_default`): the parts' rollouts run batches of 4 and 3 against
    # one of 7, whose matmuls may round apart (by a few u·|x|; in float32 that was 3e-7 of
    # the MSE under a shape-dependent BLAS). 1e-9 is ~1e6 u, far above that and far below
    # any pooling mistake (a wrong weight moves these by > 1%).
    for key in ("mse", "rmse", "mse_vs_time", "huber"):
        assert got[key] == pytest.approx(whole[key], rel=1e-9), key
    bigger = evaluate(model, synthetic(2, 9, seed=3, nodes=5), norm, solver=solver)
    mixed = pooled([each[0], bigger], [3, 5])
    weights = [4 * 5 * 3, 2 * 8 * 5]  # K · (T − 1) · N (the same D)
    assert mixed.mse == pytest.approx(
        (each[0].mse * weights[0] + bigger.mse * weights[1]) / sum(weights), rel=1e-12)
    assert len(mixed.mse_vs_time) == 9
    assert mixed.mse_vs_time[8] == pytest.approx(bigger.mse_vs_time[8], rel=1e-12)
    assert pooled([bigger], [5]) is bigger


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
