"""Benchmark `mpnode generate` on every preset at paper scale against a scipy loop.

For each preset this generates the full dataset with `mpnode_cli.data.generate.generate`
(batched Tsit5 in torch, float64), then solves a subset of the same trajectories (same
graphs, parameters and initial states, read back from the file) one at a time with
`scipy.integrate.solve_ivp(method="DOP853")` at the same rtol/atol and a numpy right-hand
side, and extrapolates the scipy time linearly to all K trajectories. The ratio is
scipy-loop time / our generate time (file writing included). It also reports the largest
difference between the two solutions on the subset, as a check that both solved the same
problem.

Usage:
    .venv/bin/python bench/generate.py                    # every preset, 20 scipy trajectories
    .venv/bin/python bench/generate.py --presets lorenz10 gene-ba-8x8 --scipy-trajectories 50

Writes `bench/results/generate.md`. Target: ≥ 20× faster than the scipy loop on lorenz10
and gene-ba-8x8.
"""

from __future__ import annotations

import argparse
import gc
import os
import platform
import tempfile
import time
from datetime import UTC, datetime
from pathlib import Path

import numpy as np
import torch
from scipy.integrate import solve_ivp

from mpnode_cli.config.generate import GenerateConfig
from mpnode_cli.data.generate import generate, resolve_generate_config
from mpnode_cli.data.hdf5 import Dataset, read_dataset
from mpnode_cli.data.presets import PRESETS, get_preset

RESULTS = Path(__file__).parent / "results" / "generate.md"


def numpy_rhs(ds: Dataset, k: int):
    """The right-hand side of trajectory k as `f(t, y [N·D]) -> [N·D]`, written from the
    equations in numpy (not from the torch code), for scipy."""
    a = ds.adjacency[ds.graph_index[k]].astype(np.float64)  # [N, N]
    n, d = ds.num_nodes, ds.node_dim
    p = ds.scalar_params
    if ds.system == "pendulum":
        degree = a.sum(axis=1)

        def f(t, y):
            th, th_dot = y.reshape(n, d).T
            spring = a @ np.sin(th) - degree * np.sin(th)
            num = p["m"] * np.sin(th) * (p["l"] * th_dot**2 - p["g"]) + p["k"] * p["l"] * spring
            return np.stack([th_dot, num / (p["m"] * p["l"] * np.cos(th))], axis=1).ravel()

    elif ds.system == "lorenz":
        h = ds.params["coupling"][ds.graph_index[k]]  # [3N, 3N]

        def f(t, y):
            x, yy, z = y.reshape(n, 3).T
            own = np.stack(
                [p["sigma"] * (yy - x), x * (p["rho"] - z) - yy, x * yy - p["beta"] * z], axis=1
            )
            return own.ravel() + h @ y

    elif ds.system == "gene":

        def f(t, y):
            return -p["b"] * y ** p["f"] + a @ (y ** p["h"] / (1.0 + y ** p["h"]))

    elif ds.system == "kuramoto":
        omega = ds.params["omega"][ds.graph_index[k]]  # [3]

        def f(t, y):
            th = y.reshape(n, 3)
            diff = th[None, :, :] - th[:, None, :]  # [N, N, 3]: θ_j − θ_i
            return (omega + p["K"] * (a[:, :, None] * np.sin(diff)).sum(axis=1)).ravel()

    else:
        raise ValueError(f"no numpy right-hand side for {ds.system}")
    return f


def scipy_loop(ds: Dataset, subset: np.ndarray, rtol: float, atol: float):
    """Solve `subset` one trajectory at a time; returns (seconds, max abs diff from ds.states)."""
    t_span = (float(ds.time[0]), float(ds.time[-1]))
    max_diff = 0.0
    tic = time.perf_counter()
    for k in subset:
        y0 = ds.states[k, 0].reshape(-1)
        sol = solve_ivp(
            numpy_rhs(ds, k), t_span, y0, method="DOP853", t_eval=ds.time, rtol=rtol, atol=atol
        )
        ys = sol.y.T.reshape(ds.states.shape[1:])  # [T, N, D]
        max_diff = max(max_diff, float(np.abs(ys - ds.states[k]).max()))
    return time.perf_counter() - tic, max_diff


def bench_preset(name: str, folder: Path, n_scipy: int) -> dict:
    # float64 storage so that the stored initial states are exactly the solved ones.
    config = resolve_generate_config(
        GenerateConfig(**{**get_preset(name), "out": folder / f"{name}.h5", "dtype": "float64"})
    )
    # Each timed part starts from a collected heap. Otherwise the garbage of the previous
    # preset's scipy loop and file reads sets off a full collection inside the next timed
    # part (a scan of every object of torch, scipy and networkx: ~0.09 s, a third of
    # gene-ba-8x8's generate), which `mpnode generate` in its own process does not pay.
    gc.collect()
    summary = generate(config, overwrite=True)
    ds = read_dataset(summary.path)
    subset = np.random.default_rng(0).choice(ds.num_trajectories, n_scipy, replace=False)
    gc.collect()
    scipy_seconds, max_diff = scipy_loop(ds, np.sort(subset), config.solver.rtol,
                                         config.solver.atol)
    scipy_all = scipy_seconds / n_scipy * ds.num_trajectories
    return {
        "preset": name,
        "K×T×N×D": "×".join(map(str, ds.states.shape)),
        "G": ds.num_graphs,
        "ours s": summary.seconds,
        "solve s": summary.solve_seconds,
        "RHS evals": summary.n_f_evals,
        "redrawn": summary.failed + summary.rejected,
        f"scipy s ({n_scipy})": scipy_seconds,
        "scipy s (all, extrap.)": scipy_all,
        "speed-up": scipy_all / summary.seconds,
        "max abs diff": max_diff,
    }


def markdown(rows: list[dict], n_scipy: int) -> str:
    head = list(rows[0])
    fmt = {
        float: lambda v: f"{v:.3g}" if abs(v) < 0.01 else f"{v:.2f}",
        int: lambda v: f"{v:,}",
        str: str,
    }
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for row in rows:
        lines.append("| " + " | ".join(fmt[type(v)](v) for v in row.values()) + " |")
    torch_threads = torch.get_num_threads()
    return "\n".join([
        "# `mpnode generate` at paper scale vs. a scipy loop",
        "",
        f"- date: {datetime.now(UTC).isoformat(timespec='seconds')}",
        f"- machine: {platform.processor() or platform.machine()}, {os.cpu_count()} CPUs, "
        f"torch {torch.__version__} ({torch_threads} threads), numpy {np.__version__}",
        "- ours: `generate(preset)` end to end (graphs, batched Tsit5 in float64 at the "
        "preset's rtol/atol, redraws, HDF5 write), CPU.",
        f"- scipy: `solve_ivp(method='DOP853')` at the same rtol/atol with a numpy "
        f"right-hand side, looped over {n_scipy} randomly chosen trajectories of the same "
        "dataset; **the 'all' column is that time extrapolated linearly to K trajectories**, "
        "not measured.",
        "- speed-up = scipy (all, extrapolated) / ours. max abs diff = largest difference "
        "between the two solutions on the subset.",
        "- target: ≥ 20× on lorenz10 and gene-ba-8x8.",
        "",
        *lines,
        "",
    ])  # fmt: skip


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    # The quadrotor swarm is closed-loop (no right-hand side on its nodes for scipy to solve).
    compared = [name for name, preset in PRESETS.items() if preset["system"] != "quadrotor"]
    parser.add_argument("--presets", nargs="*", default=compared, choices=compared)
    parser.add_argument("--scipy-trajectories", type=int, default=20)
    parser.add_argument("--out", type=Path, default=RESULTS)
    args = parser.parse_args()

    rows = []
    with tempfile.TemporaryDirectory() as folder:
        for name in args.presets:
            row = bench_preset(name, Path(folder), args.scipy_trajectories)
            rows.append(row)
            print(
                f"{name:>16}: ours {row['ours s']:7.2f} s, scipy (extrap.) "
                f"{row['scipy s (all, extrap.)']:8.2f} s, ×{row['speed-up']:.1f}, "
                f"max abs diff {row['max abs diff']:.2e}",
                flush=True,
            )
    text = markdown(rows, args.scipy_trajectories)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(text)
    print(f"\n{text}\nwrote {args.out}")


if __name__ == "__main__":
    main()
