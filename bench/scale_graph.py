"""Peak memory of `mpnode generate` and one training epoch on large sparse graphs.

Kuramoto oscillators (3 phases per node) on one Barabási–Albert graph (m = 5, mean degree
≈ 10) of N = 1 000, 3 000 and 10 000 nodes: a handful of trajectories over a short
horizon are generated with `mpnode generate`, then `mpnode train --epochs 1` (MP-NODE with
the system's recommended PNA aggregation, small batches, solver not compiled) trains on
them. Each command runs in its own subprocess, and its peak resident set size is that
process's `ru_maxrss` (`os.wait4`), so the numbers are the CLI's own, imports included.

Graphs above 256 nodes (`mpnode_cli.limits.DENSE_GRAPH_MAX_NODES`) are held as edge lists
only, so memory should grow with the messages E (≈ 10·N here) and the states, not with N²:
the table shows what one float32 N×N matrix would take beside each peak (K of them for
the per-trajectory `[K, N, N]` batch training used to gather).

Usage:
    .venv/bin/python bench/scale_graph.py                       # N = 1000, 3000, 10000
    .venv/bin/python bench/scale_graph.py --nodes 1000 --trajectories 4

Writes `bench/results/scale-graph.md`. Target: peak RSS < 4 GiB for the 10 000-node
generate and the epoch.
"""

from __future__ import annotations

import argparse
import os
import platform
import subprocess
import sys
import tempfile
import time
from datetime import UTC, datetime
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
RESULTS = ROOT / "bench" / "results" / "scale-graph.md"
TARGET_BYTES = 4 * 1024**3


def env() -> dict[str, str]:
    """One thread per process (the machine is shared), the repository importable."""
    return {**os.environ, "OMP_NUM_THREADS": "1", "MPNODE_THREADS": "1",
            "PYTHONPATH": f"{ROOT}{os.pathsep}{os.environ.get('PYTHONPATH', '')}"}


def measured(cmd: list[str]) -> tuple[float, int]:
    """Run `cmd`; return (wall seconds, peak RSS in bytes of that process)."""
    start = time.perf_counter()
    proc = subprocess.Popen(cmd, env=env(), cwd=ROOT, stdout=subprocess.PIPE,
                            stderr=subprocess.STDOUT, text=True)
    output = proc.stdout.read()
    _, status, usage = os.wait4(proc.pid, 0)
    proc.returncode = os.waitstatus_to_exitcode(status)
    seconds = time.perf_counter() - start
    if proc.returncode != 0:
        raise RuntimeError(f"{' '.join(cmd)} failed ({proc.returncode}):\n{output[-2000:]}")
    return seconds, usage.ru_maxrss * 1024  # Linux reports KiB


def messages(path: Path) -> int:
    import h5py

    with h5py.File(path) as f:
        assert "graph/adjacency" not in f, "a graph above the threshold stored as a matrix"
        return int(f["graph/num_edges"][()].sum())


def run_size(n: int, args, work: Path) -> dict:
    data = work / f"kuramoto-n{n}.h5"
    mpnode = [sys.executable, "-m", "mpnode_cli"]
    gen_s, gen_rss = measured([*mpnode, "generate", "kuramoto", "--nodes", str(n),
                               "--trajectories", str(args.trajectories), "--t-end",
                               str(args.t_end), "--dt", str(args.dt), "--seed", "0",
                               "--out", str(data)])
    config = work / "train.toml"
    config.write_text("[solver]\ncompile = false\n")
    train_s, train_rss = measured([*mpnode, "train", str(data), "--config", str(config),
                                   "--epochs", "1", "--batch-size", str(args.batch_size),
                                   "--no-plots", "--run-dir", str(work / f"run-n{n}")])
    return {"n": n, "edges": messages(data), "file": data.stat().st_size,
            "gen_s": gen_s, "gen_rss": gen_rss, "train_s": train_s, "train_rss": train_rss}


def mib(b: float) -> str:
    return f"{b / 1024**2:,.0f}"


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--nodes", type=int, nargs="+", default=[1000, 3000, 10000])
    parser.add_argument("--trajectories", type=int, default=8)
    parser.add_argument("--t-end", type=float, default=0.5)
    parser.add_argument("--dt", type=float, default=0.05)
    parser.add_argument("--batch-size", type=int, default=2)
    args = parser.parse_args(argv)

    def git(*a: str) -> str:
        return subprocess.run(["git", *a], capture_output=True, text=True, cwd=ROOT).stdout
    commit = git("rev-parse", "--short", "HEAD").strip() + (" (dirty)" if git(
        "status", "--porcelain", "--untracked-files=no").strip() else "")
    # The CLI runs each process on one thread by default; the environment says so as well.
    threads = subprocess.run([sys.executable, "-c", "import torch; "
                              "print(torch.get_num_threads(), torch.__version__)"],
                             capture_output=True, text=True, env=env(), cwd=ROOT).stdout.split()
    load_before = "/".join(f"{x:.2f}" for x in os.getloadavg())
    _, base_rss = measured([sys.executable, "-c", "import torch, h5py, networkx, "
                                 "mpnode_cli.training.loop"])
    rows = []
    with tempfile.TemporaryDirectory(prefix="scale-graph-") as tmp:
        for n in args.nodes:
            rows.append(run_size(n, args, Path(tmp)))
            r = rows[-1]
            print(f"N={n}: E={r['edges']:,}  generate {r['gen_s']:.1f} s "
                  f"{mib(r['gen_rss'])} MiB  epoch {r['train_s']:.1f} s "
                  f"{mib(r['train_rss'])} MiB", flush=True)
    load_after = "/".join(f"{x:.2f}" for x in os.getloadavg())

    k = args.trajectories
    lines = [
        "# Peak memory on large sparse graphs: Kuramoto on Barabási–Albert graphs",
        "",
        f"- date: {datetime.now(UTC).isoformat(timespec='seconds')}",
        f"- command: `{' '.join(['python', 'bench/scale_graph.py', *(argv or sys.argv[1:])])}`",
        f"- commit: {commit}",
        f"- machine: {platform.machine()}, {os.cpu_count()} CPUs, torch "
        f"{threads[1] if len(threads) > 1 else '?'} "
        f"({threads[0] if threads else '?'} thread per process), load average (1/5/15 min) "
        f"{load_before} before, {load_after} after (a long training job shared the machine)",
        f"- data: `mpnode generate kuramoto --nodes N --trajectories {k} --t-end {args.t_end} "
        f"--dt {args.dt}` (BA m = 5, one graph; float64 Tsit5 at rtol 1e-8, atol 1e-10), "
        f"stored as float32 with edge lists only (`graph/adjacency` absent: N > 256)",
        f"- epoch: `mpnode train DATA --epochs 1 --batch-size {args.batch_size} --no-plots` "
        "with `[solver] compile = false` (MP-NODE, PNA aggregation from the recipe; the "
        "epoch-0 validation, one epoch and the test evaluation)",
        "- peak RSS: `ru_maxrss` of the command's own process (`os.wait4`), imports "
        f"included; Python with torch, h5py, networkx and mpnode imported: "
        f"{mib(base_rss)} MiB",
        f"- N×N float32: what one dense matrix of the graph would take; ×K: the per-trajectory "
        f"`[K, N, N]` adjacency the loader used to gather (K = {k})",
        "- target: peak RSS < 4 GiB for the 10 000-node generate and epoch",
        "",
        "| N | messages E | file MiB | generate s | generate peak MiB | epoch s | "
        "epoch peak MiB | N×N float32 MiB | ×K MiB |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        dense = 4 * r["n"] ** 2
        lines.append(
            f"| {r['n']:,} | {r['edges']:,} | {r['file'] / 1024**2:.1f} | {r['gen_s']:.1f} | "
            f"{mib(r['gen_rss'])} | {r['train_s']:.1f} | {mib(r['train_rss'])} | "
            f"{mib(dense)} | {mib(dense * k)} |")
    if len(rows) > 1:
        first, last = rows[0], rows[-1]
        lines += ["", f"From N = {first['n']:,} to {last['n']:,} ({last['n'] / first['n']:.0f}× "
                  f"the nodes, {last['n']**2 / first['n']**2:.0f}× N²), the peak above the "
                  f"{mib(base_rss)} MiB of imports grows "
                  f"{(last['gen_rss'] - base_rss) / max(first['gen_rss'] - base_rss, 1):.1f}× "
                  "(generate) and "
                  f"{(last['train_rss'] - base_rss) / max(first['train_rss'] - base_rss, 1):.1f}× "
                  f"(epoch), against {last['edges'] / first['edges']:.1f}× the messages."]
    biggest = max(rows, key=lambda r: r["n"])
    ok = max(biggest["gen_rss"], biggest["train_rss"]) < TARGET_BYTES
    lines += ["", f"Target {'met' if ok else 'MISSED'} at N = {biggest['n']:,}: generate "
              f"{mib(biggest['gen_rss'])} MiB, epoch {mib(biggest['train_rss'])} MiB "
              "(< 4 096 MiB)."]
    RESULTS.parent.mkdir(parents=True, exist_ok=True)
    RESULTS.write_text("\n".join(lines) + "\n")
    print("\n".join(lines))
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
