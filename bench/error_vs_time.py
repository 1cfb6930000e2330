"""Where along the horizon a model's error sits, beside the naive predictors.

Rolls a checkpoint out on a dataset split and prints, per sample time and per window of
sample times, the model's MSE beside hold x(0) and the train split's time mean (the same
units and predictors as `mpnode_cli.training.evaluate.baseline_mse`). bench/quality.py
reports one MSE per case; this shows whether the error is spread evenly or concentrated
(e.g. in the transient of the Lorenz systems, whose initial states lie near the unstable
fixed point at the origin).

Usage:
    .venv/bin/python bench/error_vs_time.py RUN_OR_CKPT DATASET [--split test] [--windows 4]
"""

from __future__ import annotations

import argparse
import itertools
import sys
from pathlib import Path

import torch

from mpnode_cli.config import train_solver
from mpnode_cli.config_upgrade import stored_solver
from mpnode_cli.data.dataset import TrajectoryData
from mpnode_cli.training.checkpoint import load_checkpoint
from mpnode_cli.training.evaluate import evaluate


def per_time(checkpoint: Path, data_path: Path, split: str) -> dict[str, torch.Tensor]:
    """`{"time", "model", "hold_x0", "time_mean"}`: `[T]` MSE per sample time (t₀ included)."""
    ckpt = load_checkpoint(checkpoint)
    model, norm = ckpt.build_model(), ckpt.build_normalizer()
    data = TrajectoryData.load(data_path)
    train, scored = data.subset("train"), data.subset(split)
    solver = stored_solver(ckpt.train_config, train_solver).model_copy(update={"compile": False})
    result = evaluate(model, scored, norm, solver=solver)
    x = norm.norm_x(scored.states.double())  # (K, T, N, D)
    mean_t = norm.norm_x(train.states.double()).mean(dim=(0, 2))  # (T, D), same sample grid
    return {
        "time": scored.time,
        "model": torch.tensor(result.mse_vs_time, dtype=torch.float64),
        "hold_x0": (x - x[:, :1]).pow(2).mean(dim=(0, 2, 3)),
        "time_mean": (x - mean_t[None, :, None, :]).pow(2).mean(dim=(0, 2, 3)),
    }


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("checkpoint", type=Path, help="a checkpoint or a run folder (best.pt)")
    parser.add_argument("dataset", type=Path)
    parser.add_argument("--split", default="test")
    parser.add_argument("--windows", type=int, default=5)
    args = parser.parse_args(argv)
    torch.set_num_threads(1)
    path = args.checkpoint
    if path.is_dir():
        path = path / "checkpoints" / "best.pt"
    r = per_time(path, args.dataset, args.split)
    t = r["time"]
    print("| window | model MSE | hold x(0) | time mean | time mean ÷ model |")
    print("|---|---:|---:|---:|---:|")
    edges = torch.linspace(1, len(t), args.windows + 1).round().long().tolist()
    for a, b in itertools.pairwise(edges):
        m, h, tm = (float(r[k][a:b].mean()) for k in ("model", "hold_x0", "time_mean"))
        print(f"| t ∈ [{float(t[a]):.2f}, {float(t[b - 1]):.2f}] | {m:.4g} | {h:.4g} | "
              f"{tm:.4g} | {tm / m:.2f} |")
    m, h, tm = (float(r[k][1:].mean()) for k in ("model", "hold_x0", "time_mean"))
    print(f"| all (t₀ excluded) | {m:.4g} | {h:.4g} | {tm:.4g} | {tm / m:.2f} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
