"""Solve a batch of coupled Lorenz systems with mpnode's Tsit5 and check it against scipy.

Run it with `.venv/bin/python examples/solver_demo.py` (after `make demo` or `make test`).
Prints a small table: per-sample status, steps, and the error against scipy's DOP853 at
tight tolerance.
"""

from __future__ import annotations

import time

import numpy as np
import torch
from rich.console import Console
from rich.table import Table
from scipy.integrate import solve_ivp

from mpnode_cli.solver import Status, solve


def lorenz(t, y):  # y: [B, 3]
    a, b, c = y.unbind(-1)
    return torch.stack((10 * (b - a), a * (28 - c) - b, a * b - 8 / 3 * c), -1)


def main() -> None:
    rng = np.random.default_rng(0)
    y0 = rng.uniform(-1, 1, size=(8, 3))
    ts = np.linspace(0.0, 2.5, 51)
    start = time.perf_counter()
    sol = solve(lorenz, torch.tensor(y0), torch.tensor(ts), rtol=1e-8, atol=1e-10)
    seconds = time.perf_counter() - start

    table = Table(title=f"mpnode Tsit5: 8 Lorenz trajectories in one batch ({seconds:.2f} s)")
    for col in ("sample", "status", "steps", "rejected", "rel. error vs scipy DOP853"):
        table.add_column(col, justify="right")
    for i in range(len(y0)):
        ref = solve_ivp(lambda t, y: lorenz(t, torch.tensor(y)[None])[0].numpy(), (0, 2.5),
                        y0[i], method="DOP853", t_eval=ts, rtol=1e-12, atol=1e-12).y.T
        err = np.linalg.norm(sol.ys[i].numpy() - ref) / np.linalg.norm(ref)
        table.add_row(str(i), Status(int(sol.status[i])).name,
                      str(int(sol.stats["n_steps"][i])), str(int(sol.stats["n_rejected"][i])),
                      f"{err:.1e}")
    Console().print(table)


if __name__ == "__main__":
    main()
