"""Ensemble benchmark: S members trained as one batched model against S separate runs.

For S = 1, 2, 5 and 10, on each dataset, `mpnode train --seeds S` (one process, one solve
for all members, `mpnode_cli.models.ensemble`) against S runs of one member each, one after
another (the same seeds). Reported per S:
- seconds per epoch (the median over epochs 2…E of the training part of the epoch,
  validation excluded, and of the whole epoch with validation), as a ratio to the mean
  epoch of the same S seeds each trained alone in the same round: S separate runs cost S ×
  that mean, so `throughput × = S / ratio`;
- the largest relative difference, over members and epochs, between a member's validation
  loss and the same seed trained alone (float32, the training precision: batched matmuls
  round otherwise than one member's, and training amplifies it; `tests/test_ensemble.py`
  checks float64 to 1e-4).

Rounds are interleaved (each round runs every S), and the table gives each ratio's median
over rounds with its min–max. One torch thread; the machine's load average before and
after is printed with the table, since the ratios assume a quiet machine.

Datasets (generated into a temporary folder, 80 trajectories, 56 of them train): gene on
3×3 BA grids (N = 9, D = 1, 21 samples) at batch 32 (2 steps an epoch, 252 node rows a
solve) and at batch 8 (7 steps, 72 rows), and Kuramoto on 10-node BA graphs (N = 10,
D = 3, 21 samples) at batch 32; mpnode's default recipe otherwise.

Usage:
    .venv/bin/python bench/ensemble.py                    # about 10 minutes
    .venv/bin/python bench/ensemble.py --sizes 1 2 --rounds 1 --epochs 3 --out /tmp/e.md
Writes `bench/results/ensemble.md`. Target: S = 5 costs at most 2.5× one member's epoch.
"""

from __future__ import annotations

import argparse
import os
import platform
import statistics
import sys
import tempfile
import time
from pathlib import Path

import torch

from mpnode_cli.config import GenerateConfig, TrainConfig
from mpnode_cli.data.generate import generate
from mpnode_cli.training.loop import train
from mpnode_cli.training.run import read_metrics

RESULTS = Path(__file__).resolve().parent / "results" / "ensemble.md"
# Each bench: the dataset, and the batch size it trains with (B·N rows a solve).
DATASETS = {
    "gene-ba9": ({"system": "gene", "grid": 3, "topology": "ba"}, 32),
    "gene-ba9-batch8": ({"system": "gene", "grid": 3, "topology": "ba"}, 8),
    "kuramoto-ba10": ({"system": "kuramoto", "nodes": 10, "topology": "ba"}, 32),
}


def make_data(root: Path, name: str, trajectories: int) -> Path:
    out = root / f"{name}.h5"
    fields = DATASETS[name][0] | {"trajectories": trajectories, "out": out, "seed": 0}
    generate(GenerateConfig(**fields))
    return out


def run(data: Path, root: Path, seeds: int, seed: int, epochs: int) -> list[dict]:
    """The metrics rows of a run of `seeds` members starting at seed `seed`."""
    run_dir = root / f"{data.stem}-S{seeds}-s{seed}-{time.monotonic_ns()}"
    train(TrainConfig(dataset=data, run_dir=run_dir, epochs=epochs, seed=seed, seeds=seeds,
                      batch_size=DATASETS[data.stem][1], plots=False,
                      solver={"compile": False}))
    return read_metrics(run_dir)


def epoch_seconds(rows: list[dict]) -> tuple[float, float, float]:
    """Median over epochs 2… of the training part and of the whole epoch, and the RHS
    evaluations of an epoch's training steps (summed over its batches)."""
    later = [r for r in rows if r["epoch"] >= 2]
    return (statistics.median(r["train_seconds"] for r in later),
            statistics.median(r["seconds"] for r in later),
            statistics.median(r["rhs_evals"] for r in later))


def bench(data: Path, root: Path, args) -> list[dict]:
    """Per S and round: the ensemble's epoch against the mean epoch of its S members' seeds
    trained alone (so S / ratio is the throughput against S separate runs); and the largest
    difference of a member's validation loss to its seed alone."""
    ratios = {s: {"train": [], "epoch": [], "evals": []} for s in args.sizes}
    gap = {s: 0.0 for s in args.sizes}
    for r in range(args.rounds):
        alone = {k: run(data, root, 1, k, args.epochs) for k in range(max(args.sizes))}
        for s in args.sizes:
            rows = run(data, root, s, 0, args.epochs)
            mine = epoch_seconds(rows)
            theirs = [epoch_seconds(alone[k]) for k in range(s)]
            for i, part in enumerate(("train", "epoch", "evals")):
                ratios[s][part].append(mine[i] / statistics.mean(t[i] for t in theirs))
            print(f"round {r + 1} {data.stem} S={s}: train {ratios[s]['train'][-1]:.2f}× "
                  f"a member alone, epoch {ratios[s]['epoch'][-1]:.2f}×", file=sys.stderr)
            for k in range(s if s > 1 else 0):
                for row, solo in zip(rows, alone[k], strict=True):
                    got = row["members"][k]["val_loss"]
                    gap[s] = max(gap[s], abs(got - solo["val_loss"]) / solo["val_loss"])
    return [{"dataset": data.stem, "S": s, "gap": gap[s] if s > 1 else None} | ratios[s]
            for s in args.sizes]


def _ratio(values: list[float]) -> str:
    return f"{statistics.median(values):.2f} ({min(values):.2f}–{max(values):.2f})"


def write_report(rows: list[dict], args, load_before, load_after) -> str:
    lines = [
        "# Ensembles: S members in one batched model against S separate runs",
        "",
        f"Written by `bench/ensemble.py {' '.join(sys.argv[1:])}` on "
        f"{time.strftime('%Y-%m-%d')}. Machine: {platform.machine()}, {os.cpu_count()} "
        f"cores, {torch.get_num_threads()} torch thread, torch {torch.__version__}, CPU, "
        f"eager (ensembles do not compile). Load average (1/5/15 min) before "
        f"{'/'.join(f'{x:.2f}' for x in load_before)}, after "
        f"{'/'.join(f'{x:.2f}' for x in load_after)}. {args.rounds} interleaved rounds of "
        f"{args.epochs} epochs; medians over rounds (min–max).",
        "",
        "`× one member` is the epoch of S members over the mean epoch of the same S seeds "
        "each trained alone (the same recipe, data and batch size) in the same round: S "
        "separate runs cost S× that, so `throughput ×` = S / ratio is what the batched "
        "model gains. `train` is "
        "the epoch's optimizer steps, `epoch` adds the validation rollouts. `max rel. gap` "
        "is the largest relative difference between a member's validation loss and its seed "
        "trained alone, over members and epochs, in float32. `RHS evals ×` is the solver's "
        "vector-field evaluations in an epoch's steps against the seeds' mean alone: one "
        "solve steps until its slowest sample is done, so the slowest member sets it.",
        "",
        "| dataset | S | train: × one member | throughput × | epoch: × one member | "
        "throughput × | RHS evals × | max rel. gap to the seed alone |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        s, gap = r["S"], "—" if r["gap"] is None else f"{r['gap']:.1e}"
        lines.append(
            f"| {r['dataset']} | {s} | {_ratio(r['train'])} | "
            f"{s / statistics.median(r['train']):.2f} | {_ratio(r['epoch'])} | "
            f"{s / statistics.median(r['epoch']):.2f} | {statistics.median(r['evals']):.2f} "
            f"| {gap} |")
    lines += ["", LIMITS]
    return "\n".join(lines) + "\n"


LIMITS = (
    "What limits it, on a CPU core: one solve for S members saves the per-operation "
    "overhead (Python, dispatch, the solver's bookkeeping) of S − 1 solves, not their "
    "arithmetic. The vector field of S members is S times one member's arithmetic, and at "
    "a few hundred node rows a solve (batch 32 × 9 or 10 nodes) a small MLP's matmuls and "
    "tanh are already most of a step, so the gain is small there; at 72 rows (batch 8) "
    "overhead dominates and S = 5 costs under 3× one member. The second limit is `RHS "
    "evals ×`: one solve runs until its slowest sample is done, so the members with the "
    "fewest steps wait for the stiffest (their finished rows are carried along). A GPU, "
    "where S·B rows cost about what B rows do, is where one solve pays most; this table "
    "has no GPU row.")


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sizes", type=int, nargs="+", default=[1, 2, 5, 10])
    parser.add_argument("--datasets", nargs="+", default=list(DATASETS), choices=DATASETS)
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument("--epochs", type=int, default=5)
    parser.add_argument("--trajectories", type=int, default=80)
    parser.add_argument("--out", type=Path, default=RESULTS)
    args = parser.parse_args(argv)
    torch.set_num_threads(1)
    load_before = os.getloadavg()
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        root = Path(tmp)
        for name in args.datasets:
            rows += bench(make_data(root, name, args.trajectories), root, args)
    text = write_report(rows, args, load_before, os.getloadavg())
    print(text)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(text)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
