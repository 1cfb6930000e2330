"""Memory and time of backpropagation through a solve against its number of steps: plain
backprop and checkpointed (`solve(..., checkpoints=C)`) against torchdiffeq's `odeint`
(backprop through dopri5) and `odeint_adjoint` (the continuous adjoint), on the same field.

Field: ẏ = ω·J y + 0.1·MLP(y) on `[B, F]` states (J: 2×2 rotation blocks, ω = 10; the MLP
F → H → H → F with tanh, float32), B = 32, F = 16, H = 128: an oscillation, so the steps
grow with the horizon. The horizon of each row is calibrated (without gradients, on our
solver) so that our solve takes about the row's number of steps; both solvers get
rtol = 1e-5, atol = 1e-6, dopri5's 5(4) pair against our Tsit5 (both 6 evaluations of f
a step). Loss: the sum of squares of the outputs at 11 times.

Each case runs in a fresh process (`--child`), so that its peak resident memory
(`getrusage` maxrss) is its own: the row's memory is the peak's growth over the process
after a short warm-up solve (imports, kernels, the field), which holds what the backward
pass needs at its fullest. Time: forward + backward, median of 3 where a row has ≤ 100
steps, else one run. f evals: calls of f in the forward pass / in forward and backward
together (the reruns of a checkpointed solve, the adjoint's backward solve). One torch
thread; the machine has 2 cores shared with other work, so read ratios within a run.

Usage: python bench/memory.py [--steps 10 100 1000 5000] [--checkpoints 16 64]
                              [--out bench/results/memory.md]
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import resource
import shlex
import statistics
import subprocess
import sys
import time
from datetime import date
from pathlib import Path

import torch

from mpnode_cli.data.atomic import atomic_text
from mpnode_cli.solver import solve

B, F, H, OMEGA = 32, 16, 128, 10.0
RTOL, ATOL, N_OUT = 1e-5, 1e-6, 11
DTYPE = torch.float32


class Field(torch.nn.Module):
    """f(t, y) = ω·J y + 0.1·MLP(y), counting its calls (t is ignored: scalar or [B])."""

    def __init__(self):
        super().__init__()
        torch.manual_seed(0)
        self.net = torch.nn.Sequential(torch.nn.Linear(F, H), torch.nn.Tanh(),
                                       torch.nn.Linear(H, H), torch.nn.Tanh(),
                                       torch.nn.Linear(H, F)).to(DTYPE)
        rot = torch.zeros(F, F, dtype=DTYPE)
        for i in range(0, F, 2):
            rot[i, i + 1], rot[i + 1, i] = OMEGA, -OMEGA
        self.register_buffer("rot_t", rot.T.contiguous())
        self.calls = 0

    def forward(self, t, y):
        self.calls += 1
        return y @ self.rot_t + 0.1 * self.net(y)


def initial_state() -> torch.Tensor:
    return torch.randn(B, F, generator=torch.Generator().manual_seed(1), dtype=DTYPE)


def our_steps(field: Field, horizon: float) -> int:
    """Our solve's steps over [0, horizon] (the most of any sample), without gradients."""
    with torch.no_grad():
        sol = solve(field, initial_state(), torch.linspace(0, horizon, N_OUT), rtol=RTOL,
                    atol=ATOL)
    return int(sol.stats["n_steps"].max())


def calibrate(steps: int, field: Field) -> float:
    """A horizon over which our solve takes about `steps` steps (two secant corrections)."""
    horizon = steps / our_steps(field, 1.0)
    for _ in range(2):
        horizon *= steps / our_steps(field, horizon)
    return horizon


def run_solver(method: str, field: Field, y0: torch.Tensor, ts: torch.Tensor,
               checkpoints: int | None):
    """One solve of `method`: `(loss, steps)` (steps None where the solver does not say)."""
    if method == "ours":
        sol = solve(field, y0, ts, rtol=RTOL, atol=ATOL, checkpoints=checkpoints)
        return sol.ys.square().sum(), int(sol.stats["n_steps"].max())
    import torchdiffeq

    odeint = torchdiffeq.odeint_adjoint if method == "adjoint" else torchdiffeq.odeint
    ys = odeint(field, y0, ts, rtol=RTOL, atol=ATOL, method="dopri5")
    return ys.square().sum(), None


def child(case: dict) -> dict:
    """Run one case in this (fresh) process: time, f evals and the peak memory's growth."""
    torch.set_num_threads(1)
    field = Field()
    y0 = initial_state().requires_grad_()
    method, checkpoints = case["method"], case["checkpoints"]
    warm_loss, _ = run_solver(method, field, y0, torch.linspace(0, 0.05, N_OUT), checkpoints)
    warm_loss.backward()
    ts = torch.linspace(0, case["horizon"], N_OUT)
    base = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss  # kB on Linux
    times, steps, calls = [], None, (0, 0)
    for _ in range(case["repeats"]):
        field.zero_grad(set_to_none=True)
        field.calls = 0
        start = time.perf_counter()
        loss, steps = run_solver(method, field, y0, ts, checkpoints)
        forward_calls = field.calls
        loss.backward()
        times.append(time.perf_counter() - start)
        calls = (forward_calls, field.calls)
        del loss
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss - base
    if steps is None:  # dopri5: 6 evaluations a step after the first two (f(y0), h0)
        steps = round((calls[0] - 2) / 6)
    return {**case, "seconds": statistics.median(times), "steps": steps,
            "f_forward": calls[0], "f_total": calls[1], "peak_mb": peak / 1024}


METHODS = {"ours": "mpnode plain backprop", "adjoint": "torchdiffeq odeint_adjoint",
           "odeint": "torchdiffeq odeint (backprop)"}


def label(row: dict) -> str:
    if row["method"] == "ours" and row["checkpoints"]:
        return f"mpnode checkpoints={row['checkpoints']}"
    return METHODS[row["method"]]


def measure_all(args) -> list[dict]:
    field = Field()
    rows = []
    for steps in args.steps:
        horizon = calibrate(steps, field)
        cases = [("ours", None), *(("ours", c) for c in args.checkpoints)]
        if not args.no_torchdiffeq:
            cases += [("odeint", None), ("adjoint", None)]
        for method, checkpoints in cases:
            case = {"target": steps, "horizon": horizon, "method": method,
                    "checkpoints": checkpoints, "repeats": 3 if steps <= 100 else 1}
            out = subprocess.run([sys.executable, __file__, "--child", json.dumps(case)],
                                 capture_output=True, text=True, check=True)
            row = json.loads(out.stdout.strip().splitlines()[-1])
            rows.append(row)
            print(f"{steps:>5} {label(row):<34} steps {row['steps']:>5}  "
                  f"{row['seconds']:8.2f} s  {1e3 * row['seconds'] / row['steps']:6.2f} ms/step"
                  f"  f {row['f_forward']:>6}/{row['f_total']:<6}  peak +{row['peak_mb']:8.1f} MB",
                  flush=True)
    return rows


def ratio(a: float, b: float) -> str:
    return f"{a / b:.2f}" if b > 0 else "–"


def table(args, rows: list[dict]) -> str:
    torch_version = torch.__version__
    try:
        import torchdiffeq
        tde = f", torchdiffeq {torchdiffeq.__version__}"
    except ImportError:
        tde = ""
    lines = [
        "# Memory and time of backpropagation through a solve, against its number of steps",
        "",
        f"{date.today().isoformat()}; {platform.machine()}, {os.cpu_count()} cores, torch "
        f"threads = 1, torch {torch_version}{tde}, Python {platform.python_version()}. Load "
        f"average (1/5/15 min) before {'/'.join(f'{x:.2f}' for x in args.load_before)}, "
        f"after {'/'.join(f'{x:.2f}' for x in args.load_after)} (the 2 cores are shared with "
        "other work: times are rough, read the ratios within a row's size).",
        "",
        f"Command: `{args.command}`",
        "",
        f"Field: ẏ = ω·J y + 0.1·MLP(y), B = {B}, F = {F}, MLP {F}→{H}→{H}→{F} (tanh), "
        f"float32, rtol = {RTOL:g}, atol = {ATOL:g}, {N_OUT} outputs; ours Tsit5, "
        "torchdiffeq dopri5. steps: ours the most of any sample; torchdiffeq's "
        "(forward f evals − 2) / 6. Time: forward + backward (median of 3 up to 100 steps, "
        "else one run). f evals: forward / forward + backward. Peak: growth of the "
        "process's maxrss over a warm-up solve, each case in a fresh process.",
        "",
        "| target steps | method | steps | f evals (fwd / total) | fwd + bwd s | ms / step "
        "| peak MB | kB / step |",
        "|---:|---|---:|---:|---:|---:|---:|---:|",
    ]
    for r in rows:
        lines.append(
            f"| {r['target']} | {label(r)} | {r['steps']} | {r['f_forward']} / {r['f_total']} "
            f"| {r['seconds']:.2f} | {1e3 * r['seconds'] / r['steps']:.2f} "
            f"| {r['peak_mb']:.1f} | {1024 * r['peak_mb'] / r['steps']:.1f} |")
    lines += ["", "Ratios (time per step and peak memory, each against the row's reference at "
              "the same target):", "",
              "| target steps | method | time / plain | memory / plain | time / odeint "
              "| memory / odeint | time / adjoint | memory / adjoint |",
              "|---:|---|---:|---:|---:|---:|---:|---:|"]
    for target in args.steps:
        group = [r for r in rows if r["target"] == target]
        refs = {key: next((r for r in group if r["method"] == m and not r["checkpoints"]), None)
                for key, m in (("plain", "ours"), ("odeint", "odeint"), ("adjoint", "adjoint"))}
        for r in group:
            cells = []
            for ref in refs.values():
                if ref is None:
                    cells += ["–", "–"]
                    continue
                cells += [ratio(r["seconds"] / r["steps"], ref["seconds"] / ref["steps"]),
                          ratio(r["peak_mb"], ref["peak_mb"])]
            lines.append(f"| {target} | {label(r)} | " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--steps", type=int, nargs="+", default=[10, 100, 1000, 5000])
    parser.add_argument("--checkpoints", type=int, nargs="+", default=[16, 64])
    parser.add_argument("--no-torchdiffeq", action="store_true")
    parser.add_argument("--out", type=Path, default=Path("bench/results/memory.md"))
    parser.add_argument("--child", help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.child:
        print(json.dumps(child(json.loads(args.child))))
        return 0
    torch.set_num_threads(1)
    args.command = shlex.join(["python", "bench/memory.py", *(sys.argv[1:] if argv is None
                                                                else argv)])
    args.load_before = os.getloadavg()
    rows = measure_all(args)
    args.load_after = os.getloadavg()
    atomic_text(args.out, table(args, rows))
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
