"""Solver benchmark: batched coupled Lorenz, our Tsit5 against named peers in the same run.

Problem: N = 10 Lorenz systems (σ=10, ρ=28, β=8/3; 30 states per sample) with weak linear
coupling ẋ = Lorenz(x) + H·x (H ∈ R^{30×30}, entries U[0,1), own 3×3 blocks zero, Frobenius
norm 0.01), t ∈ [0, 2.5] saved every 0.05, initial states U(−1, 1).

Peers: scipy `solve_ivp` (RK45, DOP853) looped per sample, torchdiffeq `dopri5`, torchode
`tsit5` (its default integral controller). Every solver gets the same tolerances and the same
right-hand side. Reported per solver and batch size: wall time (median of `--repeats`, after
one warm-up), right-hand-side evaluations and steps (max over samples; batched solvers
evaluate the whole batch per call), relative L2 error against a DOP853 rtol=atol=1e-12
reference (on the first `--ref-samples` samples), and for our solver the share of the wall
time spent inside `f` (the rest is solver overhead). A floor row per dtype and batch size times
as many evaluations of `f` as ours took, chained by Euler updates with no solver; each batched
torch solver's solver share is (wall − floor) / wall, the floor scaled to its f-evals.

Wall times are noisy on a shared 2-core machine: read the ratios between solvers of one run.

Usage: python bench/solver.py [--batches 1 64 512 4096] [--repeats 3]
                              [--out bench/results/solver.md]
"""

from __future__ import annotations

import argparse
import os
import platform
import statistics
import sys
import time
from pathlib import Path

import numpy as np
import torch

from mpnode_cli.solver import solve

N_NODES, SIGMA, RHO, BETA = 10, 10.0, 28.0, 8.0 / 3.0
T_END, DT_SAVE = 2.5, 0.05


def coupling(seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    h = rng.random((3 * N_NODES, 3 * N_NODES))
    for i in range(N_NODES):
        h[3 * i : 3 * i + 3, 3 * i : 3 * i + 3] = 0.0
    return h * (0.01 / np.linalg.norm(h))


def torch_rhs(h_np: np.ndarray, dtype: torch.dtype):
    """f(t, y [B, 30]) -> [B, 30], shared by our solver, torchdiffeq and torchode."""
    h_t = torch.tensor(h_np.T, dtype=dtype)

    def f(t, y):
        x = y.view(y.shape[0], N_NODES, 3)
        a, b, c = x.unbind(-1)
        d = torch.stack((SIGMA * (b - a), a * (RHO - c) - b, a * b - BETA * c), dim=-1)
        return torch.addmm(d.view(y.shape[0], -1), y, h_t)

    return f


def numpy_rhs(h_np: np.ndarray):
    def f(t, y):
        x = y.reshape(N_NODES, 3)
        a, b, c = x[:, 0], x[:, 1], x[:, 2]
        d = np.stack((SIGMA * (b - a), a * (RHO - c) - b, a * b - BETA * c), axis=-1)
        return d.reshape(-1) + h_np @ y

    return f


class Counted:
    """Wraps f to count batched calls and the seconds spent inside it."""

    def __init__(self, f):
        self.f, self.calls, self.seconds = f, 0, 0.0

    def __call__(self, t, y):
        start = time.perf_counter()
        out = self.f(t, y)
        self.seconds += time.perf_counter() - start
        self.calls += 1
        return out


def median_time(run, repeats: int) -> tuple[float, object]:
    run()  # warm-up
    times, out = [], None
    for _ in range(repeats):
        start = time.perf_counter()
        out = run()
        times.append(time.perf_counter() - start)
    return statistics.median(times), out


def rel_l2(ys: np.ndarray, ref: np.ndarray) -> float:
    return float(np.linalg.norm(ys - ref) / np.linalg.norm(ref))


def bench_ours(f, y0, ts, rtol, atol, repeats):
    wall, sol = median_time(lambda: solve(f, y0, ts, rtol=rtol, atol=atol), repeats)
    counted = Counted(f)
    start = time.perf_counter()
    solve(counted, y0, ts, rtol=rtol, atol=atol)
    share = counted.seconds / (time.perf_counter() - start)
    return wall, sol.ys.double().numpy(), int(sol.stats["n_f_evals"].max()), int(
        sol.stats["n_steps"].max()), share


def bench_ours_compiled(f, y0, ts, rtol, atol, repeats):
    """The same solver with its step function compiled by torch.compile (inductor)."""
    from mpnode_cli.solver.compile_cache import CompileCache

    compiled = CompileCache()  # one for every call, which reuse its graphs
    start = time.perf_counter()
    solve(f, y0, ts, rtol=rtol, atol=atol, compile=compiled)  # compiles (this f/shape)
    compile_s = time.perf_counter() - start
    wall, sol = median_time(lambda: solve(f, y0, ts, rtol=rtol, atol=atol, compile=compiled),
                            repeats)
    return (wall, sol.ys.double().numpy(), int(sol.stats["n_f_evals"].max()),
            int(sol.stats["n_steps"].max()), None, compile_s)


def bench_floor(f, y0, n_evals: int, repeats: int) -> float:
    """Seconds for `n_evals` evaluations of `f` chained by Euler updates: no solver."""

    def run():
        y, t = y0, torch.zeros(len(y0), dtype=torch.float64)
        for _ in range(n_evals):
            y = y + 1e-3 * f(t, y)
        return y

    return median_time(run, repeats)[0]


def bench_torchdiffeq(f, y0, ts, rtol, atol, repeats):
    import torchdiffeq

    counted = Counted(f)
    wall, ys = median_time(
        lambda: torchdiffeq.odeint(counted, y0, ts.to(y0.dtype), rtol=rtol, atol=atol,
                                   method="dopri5"), repeats)
    calls = counted.calls // (repeats + 1)
    return wall, ys.transpose(0, 1).double().numpy(), calls, None, None


def bench_torchode(f, y0, ts, rtol, atol, repeats):
    import torchode

    term = torchode.ODETerm(f)
    step = torchode.Tsit5(term=term)
    ctrl = torchode.IntegralController(atol=atol, rtol=rtol, term=term)
    adjoint = torchode.AutoDiffAdjoint(step, ctrl)
    problem = torchode.InitialValueProblem(y0=y0, t_eval=ts.to(y0.dtype).expand(len(y0), -1))
    wall, sol = median_time(lambda: adjoint.solve(problem), repeats)
    return (wall, sol.ys.double().numpy(), int(sol.stats["n_f_evals"].max()),
            int(sol.stats["n_steps"].max()), None)


def bench_scipy(method, h_np, y0_np, ts_np, rtol, atol, max_samples):
    from scipy.integrate import solve_ivp

    f = numpy_rhs(h_np)
    n = min(len(y0_np), max_samples)
    start = time.perf_counter()
    ys, nfev = [], 0
    for y in y0_np[:n]:
        r = solve_ivp(f, (ts_np[0], ts_np[-1]), y, method=method, t_eval=ts_np, rtol=rtol,
                      atol=atol)
        ys.append(r.y.T)
        nfev = max(nfev, r.nfev)
    wall = (time.perf_counter() - start) * len(y0_np) / n  # extrapolated when n < B
    return wall, np.stack(ys), nfev, None, None, n


def reference(h_np, y0_np, ts_np, n):
    from scipy.integrate import solve_ivp

    f = numpy_rhs(h_np)
    return np.stack([
        solve_ivp(f, (ts_np[0], ts_np[-1]), y, method="DOP853", t_eval=ts_np, rtol=1e-12,
                  atol=1e-12).y.T for y in y0_np[:n]
    ])


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--batches", type=int, nargs="+", default=[1, 64, 512, 4096])
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--ref-samples", type=int, default=32)
    parser.add_argument("--scipy-samples", type=int, default=64,
                        help="scipy is looped over at most this many samples, then extrapolated")
    parser.add_argument("--threads", type=int, default=1,
                        help="torch threads (1: the thread policy of every mpnode verb)")
    parser.add_argument("--compile-batches", type=int, nargs="*", default=[1, 512],
                        help="batch sizes at which the torch.compile variant is also timed")
    parser.add_argument("--out", type=Path, default=Path("bench/results/solver.md"))
    args = parser.parse_args(argv)
    torch.set_num_threads(args.threads)
    args.load_before = os.getloadavg()

    h_np = coupling()
    ts_np = np.arange(0.0, T_END + DT_SAVE / 2, DT_SAVE)
    ts = torch.tensor(ts_np, dtype=torch.float64)
    rng = np.random.default_rng(1)
    y0_all = rng.uniform(-1, 1, size=(max(args.batches), 3 * N_NODES))
    n_ref = min(args.ref_samples, len(y0_all))
    ref = reference(h_np, y0_all, ts_np, n_ref)

    rows = []
    settings = [(torch.float64, 1e-6, 1e-8), (torch.float32, 1e-4, 1e-6)]
    for dtype, rtol, atol in settings:
        f = torch_rhs(h_np, dtype)
        for batch in args.batches:
            y0_np = y0_all[:batch]
            y0 = torch.tensor(y0_np, dtype=dtype)
            nr = min(n_ref, batch)
            results = {
                "mpnode tsit5": bench_ours(f, y0, ts, rtol, atol, args.repeats),
                "torchode tsit5": bench_torchode(f, y0, ts, rtol, atol, args.repeats),
                "torchdiffeq dopri5": bench_torchdiffeq(f, y0, ts, rtol, atol, args.repeats),
            }
            if batch in args.compile_batches:
                *res, compile_s = bench_ours_compiled(f, y0, ts, rtol, atol, args.repeats)
                results[f"mpnode tsit5 + torch.compile (compile {compile_s:.0f} s)"] = tuple(res)
            for method in ("RK45", "DOP853"):
                wall, ys, nfev, steps, share, n = bench_scipy(
                    method, h_np, y0_np, ts_np, rtol, atol, args.scipy_samples)
                name = f"scipy {method} loop" + (f" (×{batch / n:.0f} extrap.)" if n < batch
                                                 else "")
                results[name] = (wall, ys, nfev, steps, share)
            ours, ours_evals = results["mpnode tsit5"][0], results["mpnode tsit5"][2]
            floor = bench_floor(f, y0, ours_evals, args.repeats)
            dt_name = str(dtype).replace("torch.", "")
            for name, (wall, ys, nfev, steps, share) in results.items():
                err = rel_l2(ys[:nr], ref[:nr])
                batched = not name.startswith("scipy")  # one call of f per step for the batch
                solver_share = (wall - floor * nfev / ours_evals) / wall if batched else None
                rows.append((dt_name, batch, name, wall, wall / ours, nfev, steps, err, share,
                             solver_share))
                print(f"{dt_name:8s} B={batch:5d} {name:32s} {wall:8.3f}s "
                      f"x{wall / ours:6.2f} f-evals {nfev:6d} err {err:.1e}"
                      + (f" f-share {share:.0%}" if share is not None else "")
                      + (f" solver share {solver_share:.0%}" if batched else ""), flush=True)
            rows.append((dt_name, batch, f"RHS floor: {ours_evals} evaluations chained, no "
                         "solver", floor, floor / ours, ours_evals, None, None, None, None))

    args.load_after = os.getloadavg()
    write_table(args, rows)
    return 0


def write_table(args, rows):
    import torchdiffeq
    import torchode

    lines = [
        "# Solver benchmark: batched coupled Lorenz (N=10, 30 states), t ∈ [0, 2.5], "
        "saved every 0.05",
        "",
        f"Machine: {platform.processor() or platform.machine()}, {args.threads} threads, "
        f"torch {torch.__version__}, torchode {getattr(torchode, '__version__', '?')}, "
        f"torchdiffeq {torchdiffeq.__version__}, Python {sys.version.split()[0]}, "
        f"{time.strftime('%Y-%m-%d')}. Load average (1/5/15 min) before "
        f"{'/'.join(f'{x:.2f}' for x in args.load_before)}, after "
        f"{'/'.join(f'{x:.2f}' for x in args.load_after)}. "
        f"Median of {args.repeats} after a warm-up. `× ours` = wall time / mpnode's wall "
        "time in the same configuration (higher = slower than mpnode). f-evals and steps: max "
        "over samples (batched solvers call f on the whole batch). rel. L2 error against "
        f"scipy DOP853 at rtol=atol=1e-12 on the first {args.ref_samples} samples. f-share: "
        "fraction of mpnode's wall time spent inside the right-hand side. solver share: "
        "(wall − floor) / wall, the floor (as many f-evals as ours, chained, no solver) scaled "
        "to the row's f-evals.",
        "",
        "float64 runs use rtol=1e-6, atol=1e-8; float32 runs rtol=1e-4, atol=1e-6.",
        "",
        "| dtype | B | solver | wall s | × ours | f-evals | steps | rel. L2 error | f-share | "
        "solver share |",
        "|---|---:|---|---:|---:|---:|---:|---:|---:|---:|",
    ]

    def pct(x):
        return f"{x:.0%}" if x is not None else "–"

    for dt, b, name, wall, ratio, nfev, steps, err, share, solver_share in rows:
        lines.append(
            f"| {dt} | {b} | {name} | {wall:.3f} | {ratio:.2f} | {nfev} | "
            f"{steps if steps is not None else '–'} | "
            f"{f'{err:.1e}' if err is not None else '–'} | {pct(share)} | {pct(solver_share)} |")
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text("\n".join(lines) + "\n")
    print(f"wrote {args.out}")


if __name__ == "__main__":
    sys.exit(main())
