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
  round otherwise than one member's, and training amplifies it; `tests/models/test_ensemble.py`
  checks float64 to 1e-4).

Rounds are interleaved (each round runs every S), and the table gives each ratio's median
over rounds with its min–max. One torch thread; the machine's load average before and
after is printed with the table, since the ratios assume a quiet machine.

Datasets (generated into a temporary folder, 80 trajectories, 56 of them train): gene on
3×3 BA grids (N = 9, D = 1, 21 samples) at batch 32 (2 steps an epoch, 252 node rows a
solve) and at batch 8 (7 steps, 72 rows), and Kuramoto on 10-node BA graphs (N = 10,
D = 3, 21 samples) at batch 32; mpnode's default recipe otherwise.

A second part (`--part step`, also in the default run) takes the epochs apart on one
training step (forward and backward through one solve) of gene-ba9 at batch B, with the
weights of a short run of S members, against one member alone at B trajectories:
- `S members`: the ensemble as training runs it (`Ensemble.member_rollouts`);
- `S copies of one member`: the ensemble with every member's weights member 0's, so every
  member takes member 0's steps: the same solve without the members' differing step counts;
- `one model, S·B rows`: member 0 alone on its batch repeated S times, the same steps and
  the same rows with plain weights: the arithmetic any one-solve ensemble must do, with
  none of the member batching. This is the floor of the S members' step on this machine.

Usage:
    .venv/bin/python bench/ensemble.py                    # about 2 minutes (quiet machine)
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

from mpnode_cli.config.generate import GenerateConfig
from mpnode_cli.config.train import TrainConfig
from mpnode_cli.data.dataset import TrajectoryData
from mpnode_cli.data.generate import generate
from mpnode_cli.models.ensemble import Ensemble
from mpnode_cli.training.checkpoint import load_checkpoint
from mpnode_cli.training.loop import train
from mpnode_cli.training.run import checkpoint_path, read_metrics

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


class StepProblem:
    """One training step of gene-ba9 at batch B: S members (the weights of a short run of S
    members), S copies of member 0, and member 0 alone at B and at S·B trajectories."""

    def __init__(self, data: Path, root: Path, members: int, epochs: int):
        run_dir = root / f"step-S{members}"
        batch = DATASETS[data.stem][1]
        config = TrainConfig(dataset=data, run_dir=run_dir, epochs=epochs, seed=0,
                             seeds=members, batch_size=batch, plots=False,
                             solver={"compile": False})
        train(config)
        ckpt = load_checkpoint(checkpoint_path(run_dir, "last"))
        self.ensemble = ckpt.build_model()
        self.solver = config.solver
        trajectories = TrajectoryData.load(data).subset("train")
        normalizer = ckpt.build_normalizer()
        self.x = normalizer.norm_x(trajectories.states[:batch])  # (B, T, N, D)
        self.graph = trajectories.take(torch.arange(batch)).graph()
        self.ts = trajectories.time.to(torch.float64)

    def _members(self, s: int, same: bool) -> Ensemble:
        if same:
            return Ensemble([self.ensemble.members[0]] * s)
        return Ensemble(list(self.ensemble.members[:s]))

    def ensemble_step(self, s: int, same: bool = False) -> int:
        """Forward and backward of S members (or S copies of member 0) in one solve."""
        model = self._members(s, same)
        model.zero_grad(set_to_none=True)
        xs = self.x.expand(s, *self.x.shape)
        outs = model.member_rollouts(xs[:, :, 0], self.ts, [self.graph] * s, None,
                                     range(s), solver=self.solver)
        sum(torch.nn.functional.mse_loss(o.states, self.x) for o in outs).backward()
        return outs[0].n_f_evals

    def alone_step(self, k: int, repeat: int = 1) -> int:
        """Forward and backward of member k alone, on its batch repeated `repeat` times."""
        model = self.ensemble.members[k]
        model.zero_grad(set_to_none=True)
        x = self.x.repeat(repeat, 1, 1, 1)
        graph = self.graph.repeat(repeat, 1, 1)
        out = model.rollout(x[:, 0], self.ts, graph, solver=self.solver)
        torch.nn.functional.mse_loss(out.states, x).backward()
        return out.n_f_evals


def _timed(fn, repeats: int) -> float:
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return statistics.median(times)


def bench_step(data: Path, root: Path, args) -> list[dict]:
    """Per S > 1 and round: each variant's step over the mean step of the S seeds alone
    (member 0's alone for the variants that use member 0's weights only)."""
    problem = StepProblem(data, root, max(args.sizes), args.step_epochs)
    sizes = [s for s in args.sizes if s > 1]
    variants = {
        "S members": lambda s: problem.ensemble_step(s),
        "S copies of one member": lambda s: problem.ensemble_step(s, same=True),
        "one model, S·B rows": lambda s: problem.alone_step(0, s),
    }
    for s in sizes:  # warm up
        for fn in variants.values():
            fn(s)
    ratios = {(v, s): [] for v in variants for s in sizes}
    evals = {}
    for _ in range(args.rounds):
        alone = [_timed(lambda k=k: problem.alone_step(k), args.repeats)
                 for k in range(max(sizes))]
        for s in sizes:
            for v, fn in variants.items():
                t = _timed(lambda f=fn, s=s: f(s), args.repeats)
                base = statistics.mean(alone[:s]) if v == "S members" else alone[0]
                ratios[(v, s)].append(t / base)
    alone_evals = [problem.alone_step(k) for k in range(max(sizes))]
    for s in sizes:
        for v, fn in variants.items():
            base = statistics.mean(alone_evals[:s]) if v == "S members" else alone_evals[0]
            evals[(v, s)] = fn(s) / base
    return [{"S": s, "variant": v, "ratio": ratios[(v, s)], "evals": evals[(v, s)]}
            for s in sizes for v in variants]


def _ratio(values: list[float]) -> str:
    return f"{statistics.median(values):.2f} ({min(values):.2f}–{max(values):.2f})"


def write_report(rows: list[dict], step_rows: list[dict], args, load_before,
                 load_after) -> str:
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
    if step_rows:
        lines += ["", STEP_TEXT.format(repeats=args.repeats), "",
                  "| S | variant | step: × one member alone | RHS evals × |",
                  "|---|---|---|---|"]
        for r in step_rows:
            lines.append(f"| {r['S']} | {r['variant']} | {_ratio(r['ratio'])} | "
                         f"{r['evals']:.2f} |")
    return "\n".join(lines) + "\n"


LIMITS = (
    "What limits it, on a CPU core (the step table below takes one step apart): one solve "
    "for S members saves the per-operation overhead of S − 1 solves (Python, dispatch, the "
    "solver's bookkeeping), not their arithmetic, and the vector field of S members is S "
    "times one member's arithmetic. At a few hundred node rows a solve (batch 32 × 9 or 10 "
    "nodes) a small MLP's matmuls and tanh are already most of a step, so the gain is small "
    "there; at 72 rows (batch 8) overhead dominates and the gain is larger. The second "
    "limit is `RHS evals ×`: one solve runs until its slowest sample is done. Once at most "
    "half its rows still run, the solve goes on with the members that still run only "
    "(compaction), but each of the slowest member's extra steps still costs a step's "
    "overhead. A GPU, where S·B rows cost about what B rows do, is where one solve pays "
    "most; this table has no GPU row.")


STEP_TEXT = (
    "One training step taken apart (gene-ba9, batch 32, 252 node rows a member; weights "
    "of a 2-epoch run of the members; forward and backward through one solve; each round "
    "times every variant's step {repeats} times and takes the median; the table gives the "
    "median over rounds of its ratio to one member alone, min–max over rounds). `S "
    "members` is the ensemble as training runs it, against the mean step of the same seeds "
    "alone. `S copies of one member` gives every member member 0's weights, so the members "
    "take member 0's steps: what is left is the member batching. `one model, S·B rows` is "
    "member 0 alone on its batch repeated S times: the same steps and rows with plain "
    "weights, the arithmetic any one-solve ensemble does; it is the floor of the first "
    "row on this machine, and where it is above 2.5 no one-solve ensemble meets the "
    "target on one CPU thread.")


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sizes", type=int, nargs="+", default=[1, 2, 5, 10])
    parser.add_argument("--datasets", nargs="+", default=list(DATASETS), choices=DATASETS)
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument("--epochs", type=int, default=5)
    parser.add_argument("--trajectories", type=int, default=80)
    parser.add_argument("--out", type=Path, default=RESULTS)
    parser.add_argument("--part", choices=["all", "epochs", "step"], default="all")
    parser.add_argument("--repeats", type=int, default=5, help="steps timed per round")
    parser.add_argument("--step-epochs", type=int, default=2,
                        help="epochs of the run whose weights the step part uses")
    args = parser.parse_args(argv)
    torch.set_num_threads(1)
    load_before = os.getloadavg()
    rows, step_rows = [], []
    with tempfile.TemporaryDirectory() as tmp:
        root = Path(tmp)
        for name in args.datasets:
            data = make_data(root, name, args.trajectories)
            if args.part in ("all", "epochs"):
                rows += bench(data, root, args)
            if args.part in ("all", "step") and name == "gene-ba9":
                step_rows = bench_step(data, root, args)
    text = write_report(rows, step_rows, args, load_before, os.getloadavg())
    print(text)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(text)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
