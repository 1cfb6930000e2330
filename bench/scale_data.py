"""Datasets larger than memory: sharded generation and streamed training, measured.

1. **Generation against shard count.** `mpnode generate lorenz --nodes 10` with K
   trajectories (about 30 s in one process here) as n = 1 and n = 2 shards, the n shard
   processes started together (`--shard i/n`, one torch thread each), timed from the
   first start to the last exit (process start-up and file writing included). Reported:
   trajectories per second and the speed-up over n = 1. The n = 2 shards are then merged
   (`mpnode merge`) and the merged states compared bit for bit with the n = 1 file.
2. **Streamed against in-memory epochs.** `mpnode_cli.training.loop.train` on lorenz with
   3 nodes (K trajectories × 51 samples, the default recipe, uncompiled), in memory and
   with `stream = true`, in interleaved rounds (each round trains both from the same seed);
   an epoch's time is the loop's `seconds` (training and validation), median over the
   epochs after the first; `× memory` is the median over rounds of the per-round ratio.
   The dataset file is in the operating system's page cache (it was just written), so
   streaming here measures reading through HDF5 and the prefetch, not a cold disk.

Usage:
    .venv/bin/python bench/scale_data.py                       # both parts (about 5 minutes)
    .venv/bin/python bench/scale_data.py --gen-trajectories 1000 --train-rounds 1 --out /tmp/s.md

Writes `bench/results/scale-data.md`. Target: streamed epochs ≤ 1.3× in-memory ones.
"""

from __future__ import annotations

import argparse
import os
import platform
import shlex
import statistics
import subprocess
import sys
import tempfile
import time
from datetime import datetime
from pathlib import Path

import h5py
import torch

ROOT = Path(__file__).resolve().parent.parent
RESULTS = ROOT / "bench" / "results" / "scale-data.md"


def generate_shards(folder: Path, n: int, trajectories: int) -> float:
    """Seconds for n shard processes of one dataset, started together."""
    env = {**os.environ, "OMP_NUM_THREADS": "1", "MPNODE_THREADS": "1",
           "PYTHONPATH": str(ROOT)}
    command = [sys.executable, "-m", "mpnode_cli", "generate", "lorenz", "--nodes", "10",
               "--trajectories", str(trajectories), "--t-end", "5", "--dt", "0.1",
               "--chunk-size", "1024", "-o", str(folder / f"n{n}.h5"), "--json"]
    start = time.perf_counter()
    procs = [subprocess.Popen([*command, "--shard", f"{i}/{n}"], env=env,
                              stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
             for i in range(n)]
    for p in procs:
        _, err = p.communicate()
        if p.returncode != 0:
            raise SystemExit(f"generate failed: {err.decode()}")
    return time.perf_counter() - start


def bench_generate(folder: Path, trajectories: int, rounds: int) -> dict:
    times: dict[int, list[float]] = {1: [], 2: []}
    for _ in range(rounds):  # interleaved, so that the machine's load hits both alike
        for n in (1, 2):
            for old in folder.glob(f"n{n}.shard-*.h5"):
                old.unlink()
            times[n].append(generate_shards(folder, n, trajectories))
    ratios = [one / two for one, two in zip(times[1], times[2], strict=True)]
    rows = [{"n": n, "seconds": statistics.median(times[n]),
             "rate": trajectories / statistics.median(times[n]), "all": times[n]}
            for n in (1, 2)]
    shards = sorted(folder.glob("n2.shard-*.h5"))
    start = time.perf_counter()
    subprocess.run([sys.executable, "-m", "mpnode_cli", "merge", *map(str, shards), "-o",
                    str(folder / "merged.h5")], check=True, env={**os.environ,
                                                                 "PYTHONPATH": str(ROOT)})
    merge_seconds = time.perf_counter() - start
    with h5py.File(folder / "merged.h5") as a, h5py.File(
            folder / "n1.shard-0000-of-0001.h5") as b:
        identical = a["states"][()].tobytes() == b["states"][()].tobytes()
        size = a["states"].nbytes
    return {"rows": rows, "merge_seconds": merge_seconds, "identical": identical,
            "bytes": size, "ratio": statistics.median(ratios), "rounds": rounds}


def bench_train(folder: Path, trajectories: int, epochs: int, rounds: int) -> dict:
    from mpnode_cli.config.generate import GenerateConfig
    from mpnode_cli.config.train import TrainConfig
    from mpnode_cli.data.generate import generate
    from mpnode_cli.training.loop import train
    from mpnode_cli.training.run import read_metrics

    data = generate(GenerateConfig(system="lorenz", nodes=3, trajectories=trajectories,
                                   t_end=2.5, dt=0.05, out=folder / "train.h5")).path
    per_round: dict[bool, list[float]] = {False: [], True: []}
    losses: dict[bool, list[float]] = {}
    for r in range(rounds):
        for stream in (False, True):
            run = folder / f"run-{r}-{stream}"
            train(TrainConfig(dataset=data, run_dir=run, epochs=epochs, plots=False,
                              stream=stream, solver={"compile": False}))
            rows = [row for row in read_metrics(run) if row["epoch"] >= 2]
            per_round[stream].append(statistics.median(row["seconds"] for row in rows))
            losses[stream] = [row["val_loss"] for row in read_metrics(run)]
    ratios = [s / m for s, m in zip(per_round[True], per_round[False], strict=True)]
    return {"memory": statistics.median(per_round[False]),
            "stream": statistics.median(per_round[True]), "ratio": statistics.median(ratios),
            "ratios": ratios, "same_losses": losses[True] == losses[False],
            "trajectories": trajectories, "epochs": epochs, "rounds": rounds}


def markdown(gen: dict, tr: dict, header: dict) -> str:
    lines = [
        "# Datasets larger than memory: sharded generation, streamed training", "",
        f"Command: `{header['command']}`. Machine: {header['machine']}, {header['cores']} "
        f"cores, {header['threads']} torch thread(s) per process, torch {torch.__version__}, "
        f"Python {sys.version.split()[0]}, git {header['commit']}, {header['date']}. Load "
        f"average (1/5/15 min) before {header['load_before']}, after {header['load_after']}.",
        "", header["note"], "",
        "## Generation against shard count", "",
        f"lorenz, N = 10, {gen['trajectories']} trajectories × 51 samples, chunk size 1024; "
        "n shard processes started together, one torch thread each; wall time from the "
        f"first start to the last exit; median of {gen['rounds']} interleaved rounds "
        "(speed-up: median of the per-round ratios).", "",
        "| shards | processes | seconds (median) | seconds (each round) | trajectories/s "
        "| speed-up |",
        "|---:|---:|---:|---|---:|---:|"]
    for row in gen["rows"]:
        each = ", ".join(f"{x:.1f}" for x in row["all"])
        speedup = 1.0 if row["n"] == 1 else gen["ratio"]
        lines.append(f"| {row['n']} | {row['n']} | {row['seconds']:.1f} | {each} "
                     f"| {row['rate']:.0f} | {speedup:.2f} |")
    lines += ["", f"Merging the 2 shards ({gen['bytes'] / 2**20:.0f} MiB of states) took "
              f"{gen['merge_seconds']:.1f} s; merged states bit-identical to the 1-shard "
              f"file: {'yes' if gen['identical'] else 'NO'}.", "",
              "## Streamed against in-memory epochs", "",
              f"lorenz, N = 3, {tr['trajectories']} trajectories × 51 samples (70 % train), "
              f"default recipe (batch 32), uncompiled; {tr['epochs']} epochs per run, "
              f"{tr['rounds']} interleaved rounds; s/epoch = median of the loop's epoch "
              "seconds (training and validation) after the first epoch.", "",
              "| data | s/epoch | × memory |", "|---|---:|---:|",
              f"| in memory | {tr['memory']:.3f} | 1.00 |",
              f"| streamed (--stream) | {tr['stream']:.3f} | {tr['ratio']:.2f} |", "",
              "Per-round ratios: " + ", ".join(f"{r:.3f}" for r in tr["ratios"]) + ". "
              f"Validation losses of the two runs identical: "
              f"{'yes' if tr['same_losses'] else 'NO'}. Target: ≤ 1.3×.", ""]
    return "\n".join(lines)


def git_commit() -> str:
    def git(*a):
        return subprocess.run(["git", *a], capture_output=True, text=True, cwd=ROOT).stdout
    commit = git("rev-parse", "--short=10", "HEAD").strip() or "?"
    return commit + ("+dirty" if git("status", "--porcelain", "--untracked-files=no") else "")


def load() -> str:
    return "/".join(f"{x:.2f}" for x in os.getloadavg())


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--gen-trajectories", type=int, default=6000)
    parser.add_argument("--gen-rounds", type=int, default=2)
    parser.add_argument("--train-trajectories", type=int, default=1000)
    parser.add_argument("--epochs", type=int, default=4)
    parser.add_argument("--train-rounds", type=int, default=3)
    parser.add_argument("--note", default="", help="A line on the machine's state.")
    parser.add_argument("--out", type=Path, default=RESULTS)
    args = parser.parse_args()
    torch.set_num_threads(1)
    shown = [a if a != args.note else "..." for a in sys.argv[1:]]  # the note is below
    header = {"command": "bench/scale_data.py " + shlex.join(shown),
              "machine": platform.machine(), "cores": os.cpu_count(),
              "threads": torch.get_num_threads(), "commit": git_commit(),
              "date": datetime.now().isoformat(timespec="minutes"), "load_before": load(),
              "note": args.note}
    with tempfile.TemporaryDirectory() as tmp:
        gen = bench_generate(Path(tmp), args.gen_trajectories, args.gen_rounds)
        gen["trajectories"] = args.gen_trajectories
        for row in gen["rows"]:
            print(f"generate n={row['n']}: {row['seconds']:.1f} s, {row['rate']:.0f} traj/s")
        tr = bench_train(Path(tmp), args.train_trajectories, args.epochs, args.train_rounds)
        print(f"epochs: memory {tr['memory']:.3f} s, stream {tr['stream']:.3f} s, "
              f"ratio {tr['ratio']:.2f}")
    header["load_after"] = load()
    text = markdown(gen, tr, header)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(text)
    print(text)


if __name__ == "__main__":
    main()
