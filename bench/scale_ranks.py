"""Benchmark data-parallel training: epoch time against the number of torchrun processes.

One dataset (gene dynamics on 8×8 grids, BA graphs, the `gene-ba-8x8` preset's system at a
smaller K), one training config, run as one plain process and under
`torchrun --standalone --nproc-per-node K -m mpnode_cli train` for each K given. Each
process has one torch thread (the default thread policy). Every run trains the same global
batches from the same seed, so the per-epoch validation losses must agree (to 1e-4
relative: the sums split across ranks round differently); the table shows the largest
relative difference beside the timing. Epoch time is the median over the epochs after the
first of `train_seconds` in `metrics.jsonl` (the training pass, without validation).

Usage:
    .venv/bin/python bench/scale_ranks.py                 # K = 1, 2 (this 2-core machine)
    .venv/bin/python bench/scale_ranks.py --ranks 1 2 4 --epochs 6

Writes the "ranks" section of `bench/results/scale.md` (other sections are kept).
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import subprocess
import sys
import tempfile
import time
from datetime import UTC, datetime
from pathlib import Path

import torch

ROOT = Path(__file__).resolve().parents[1]
RESULTS = ROOT / "bench" / "results" / "scale.md"
SECTION = "ranks"


def env() -> dict[str, str]:
    path = os.pathsep.join(p for p in (str(ROOT), os.environ.get("PYTHONPATH")) if p)
    return {**os.environ, "PYTHONPATH": path, "OMP_NUM_THREADS": "1"}


def make_data(folder: Path, trajectories: int) -> Path:
    out = folder / "gene.h5"
    cmd = [sys.executable, "-m", "mpnode_cli", "generate", "gene", "--grid", "8",
           "--topology", "ba", "--trajectories", str(trajectories), "--t-end", "5",
           "--dt", "0.1", "--out", str(out)]
    subprocess.run(cmd, check=True, env=env(), capture_output=True, text=True)
    return out


def train(data: Path, run: Path, ranks: int, epochs: int, batch: int, config: Path) -> dict:
    args = ["train", str(data), "--epochs", str(epochs), "--batch-size", str(batch),
            "--no-plots", "--config", str(config), "--run-dir", str(run)]
    if ranks == 1:
        cmd = [sys.executable, "-m", "mpnode_cli", *args]
    else:
        cmd = [sys.executable, "-m", "torch.distributed.run", "--standalone",
               "--nproc-per-node", str(ranks), "-m", "mpnode_cli", *args]
    start = time.perf_counter()
    done = subprocess.run(cmd, env=env(), capture_output=True, text=True)
    wall = time.perf_counter() - start
    if done.returncode != 0:
        raise SystemExit(f"{' '.join(cmd)} failed:\n{done.stdout[-2000:]}{done.stderr[-2000:]}")
    rows = [json.loads(line) for line in (run / "metrics.jsonl").read_text().splitlines()]
    trained = [r for r in rows if r["epoch"] >= 2]  # epoch 1 carries the start-up
    return {"epoch_s": statistics.median(r["train_seconds"] for r in trained),
            "val": [r["val_loss"] for r in rows], "wall": wall}


def write_section(body: str) -> None:
    """Replace this script's section of scale.md, keeping the others."""
    start, end = f"<!-- {SECTION} -->", f"<!-- /{SECTION} -->"
    text = RESULTS.read_text() if RESULTS.exists() else "# Scale: beyond one process\n\n"
    block = f"{start}\n{body.rstrip()}\n{end}\n"
    if start in text and end in text:
        text = text[:text.index(start)] + block + text[text.index(end) + len(end) + 1:]
    else:
        text = text.rstrip() + "\n\n" + block
    tmp = RESULTS.with_suffix(".tmp")
    tmp.write_text(text)
    tmp.replace(RESULTS)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--ranks", type=int, nargs="+", default=[1, 2])
    parser.add_argument("--trajectories", type=int, default=400)
    parser.add_argument("--epochs", type=int, default=5)
    parser.add_argument("--batch-size", type=int, default=128)
    parser.add_argument("--rounds", type=int, default=2, help="interleaved rounds")
    args = parser.parse_args()
    load_before = os.getloadavg()
    commit = subprocess.run(["git", "rev-parse", "--short=10", "HEAD"], capture_output=True,
                            text=True, cwd=ROOT).stdout.strip()
    times: dict[int, list[float]] = {k: [] for k in args.ranks}
    vals: dict[int, list[float]] = {}
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp)
        data = make_data(folder, args.trajectories)
        config = folder / "config.toml"
        config.write_text("[solver]\ncompile = false\n")  # the same eager step in every run
        for r in range(args.rounds):
            for k in args.ranks:
                out = train(data, folder / f"run-{k}-{r}", k, args.epochs, args.batch_size,
                            config)
                times[k].append(out["epoch_s"])
                vals.setdefault(k, out["val"])
                print(f"round {r} ranks {k}: epoch {out['epoch_s']:.2f} s "
                      f"(process {out['wall']:.1f} s)", flush=True)
    load_after = os.getloadavg()
    base = statistics.median(times[args.ranks[0]])
    lines = [
        "## Epoch time against torchrun processes (CPU, gloo)", "",
        f"Command: `bench/scale_ranks.py --ranks {' '.join(map(str, args.ranks))} "
        f"--trajectories {args.trajectories} --epochs {args.epochs} --batch-size "
        f"{args.batch_size}`. Machine: {os.cpu_count()} cores, {platform.machine()}, one torch "
        f"thread per process, torch {torch.__version__}, Python {platform.python_version()}, "
        f"git {commit}, {datetime.now(UTC):%Y-%m-%dT%H:%M} UTC. Load average (1/5/15 min) "
        f"before {'/'.join(f'{x:.2f}' for x in load_before)}, after "
        f"{'/'.join(f'{x:.2f}' for x in load_after)}.", "",
        f"Gene dynamics on one 8×8 BA grid (N = 64), {args.trajectories} trajectories, 51 "
        f"samples, MP-NODE defaults, global batch {args.batch_size}, eager step. Epoch: median "
        f"training-pass seconds over epochs 2–{args.epochs}, median over {args.rounds} "
        "interleaved rounds. Validation: the largest relative difference of the per-epoch "
        "validation loss from the one-process run.", "",
        "| processes | epoch s | speed-up | validation vs 1 process |",
        "|---:|---:|---:|---:|"]
    for k in args.ranks:
        med = statistics.median(times[k])
        diff = max(abs(a - b) / abs(b) for a, b in zip(vals[k], vals[args.ranks[0]],
                                                        strict=True))
        lines.append(f"| {k} | {med:.2f} | {base / med:.2f}× | {diff:.1e} |")
    body = "\n".join(lines)
    print(body)
    write_section(body)


if __name__ == "__main__":
    main()
