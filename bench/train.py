"""Training benchmark: MP-NODE training steps and epochs, ours against torchdiffeq, torchode.

Two measurements, each comparing integrators in the same run (ratios, not bare seconds):

1. **Training step**: forward and backward through one whole-horizon solve of MP-NODE's
   vector field — the real `MPNODE` (hidden 32, two tanh layers, M = 3), N = 3 nodes,
   D = 3, B = 128 trajectories, 51 samples over 2.5 s, float32, rtol = atol = 1e-4, MSE
   against a fixed target — with the same weights for every integrator. Variants are run
   in interleaved rounds (each round runs every variant), and the reported time is the
   median over rounds; `× ours` is the median of the per-round ratios. Also reported: RHS
   evaluations, the states' max error against a float64 solve at 1e-10 (equal tolerance is
   not equal accuracy), and the cost of a bare chain of as many RHS evaluations forward and
   backward with no solver (the floor any integrator pays). Each row's solver share is
   (step − floor) / step, the floor scaled to that row's RHS evaluations: the part of the
   step that is the integrator's own work (stage sums, error control, outputs and their
   backward). A last row repeats ours with a busy process (one CPU-bound Python loop) beside
   it: the thread policy's test.
2. **Training epochs**: `mpnode_cli.training.loop.train` on the `lorenz3` preset (1000
   trajectories × 51 samples, 700 train) with the default recipe; only the integrator
   inside `MPNODE.rollout` differs. Seconds per epoch (median after the first, validation
   excluded), RHS evaluations per batch, and the validation loss after the last epoch, with
   the variant's own integrator and re-measured with ours at 1e-6 (a common referee).

Integrators: mpnode tsit5 (adaptive, the train default: the integral step-size controller),
mpnode with the PI controller (generate's default), mpnode with `compile` (the step through
`torch.compile`), mpnode fixed steps of one sample interval; torchdiffeq dopri5 (one step
size for the whole batch) and torchode tsit5 with its IntegralController (per-sample
steps) — backpropagation through the solver's operations in every case.

Usage:
    .venv/bin/python bench/train.py                      # both parts (about 10 minutes)
    .venv/bin/python bench/train.py --part step          # the step only (about 2 minutes)
    .venv/bin/python bench/train.py --epochs 2 --trajectories 64 --rounds 2 --out /tmp/t.md
Writes `bench/results/train.md`. Targets: the step at most 1.35× the RHS floor (a solver share
of about 25%), ≥ 2× torchdiffeq and ≥ 1.6× torchode; epochs ≥ 2× both; beside one busy
process ≤ 1.5× the time alone.
"""

from __future__ import annotations

import argparse
import contextlib
import os
import platform
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import torch

from mpnode_cli.config.generate import GenerateConfig
from mpnode_cli.config.train import TrainConfig
from mpnode_cli.data.dataset import TrajectoryData
from mpnode_cli.data.generate import generate
from mpnode_cli.data.presets import get_preset
from mpnode_cli.models.base import Rollout
from mpnode_cli.models.mpnode import MPNODE
from mpnode_cli.solver.options import SolverOptions
from mpnode_cli.training.checkpoint import load_checkpoint
from mpnode_cli.training.evaluate import evaluate
from mpnode_cli.training.loop import train
from mpnode_cli.training.run import checkpoint_path, read_config, read_metrics

RESULTS = Path(__file__).parent / "results" / "train.md"


def _peer_rollout(integrate):
    """MPNODE's rollout integrating with `integrate(f, z0, ts, rtol, atol) -> (zs, evals)`.

    `f(t [B], z [B, N, D+M])` is the model's own vector field; `zs: [B, T, N, D+M]`.
    """

    def rollout(self, x0, ts, adjacency, controls=None, *, solver, return_messages=False):
        ts = ts.to(device=x0.device, dtype=torch.float64)
        z0 = torch.cat([x0, x0.new_zeros(*x0.shape[:-1], self.message_dim)], dim=-1)
        f = self.vector_field(adjacency.to(x0.dtype))
        zs, evals = integrate(f, z0, ts, solver.rtol, solver.atol)
        d = self.node_dim
        status = torch.zeros(len(x0), dtype=torch.long, device=x0.device)
        return Rollout(zs[..., :d], zs[..., d:] if return_messages else None, status, evals)

    return rollout


def torchdiffeq_dopri5(f, z0, ts, rtol, atol):
    import torchdiffeq

    calls = [0]

    def g(t, z):  # torchdiffeq passes a scalar t and steps the batch together
        calls[0] += 1
        return f(t.expand(len(z)).to(torch.float64), z)

    zs = torchdiffeq.odeint(g, z0, ts.to(z0.dtype), rtol=rtol, atol=atol, method="dopri5")
    return zs.transpose(0, 1), calls[0]  # (T, B, ...) → (B, T, ...)


def torchode_tsit5(f, z0, ts, rtol, atol):
    import torchode

    batch, shape = z0.shape[0], z0.shape[1:]

    def g(t, y):  # torchode works on flat [B, F] states
        return f(t.to(torch.float64), y.view(batch, *shape)).reshape(batch, -1)

    term = torchode.ODETerm(g)
    adjoint = torchode.AutoDiffAdjoint(torchode.Tsit5(term=term),
                                       torchode.IntegralController(atol=atol, rtol=rtol,
                                                                   term=term))
    t_eval = ts.to(z0.dtype).expand(batch, -1)
    sol = adjoint.solve(torchode.InitialValueProblem(y0=z0.reshape(batch, -1), t_eval=t_eval))
    return sol.ys.view(batch, len(ts), *shape), int(sol.stats["n_f_evals"].max())


VARIANTS = {
    "mpnode tsit5": ({}, None),
    "mpnode tsit5, PI controller": ({"solver": {"controller": "pi"}}, None),
    "mpnode tsit5 + compile": ({"solver": {"compile": True}}, None),
    "mpnode tsit5 fixed dt=0.05": ({"solver": {"fixed_dt": 0.05}}, None),
    "torchdiffeq dopri5": ({}, torchdiffeq_dopri5),
    "torchode tsit5": ({}, torchode_tsit5),
}
STEP_VARIANTS = ("mpnode tsit5", "mpnode tsit5, PI controller", "mpnode tsit5 + compile",
                 "torchdiffeq dopri5", "torchode tsit5")
EPOCH_VARIANTS = ("mpnode tsit5", "mpnode tsit5, PI controller", "mpnode tsit5 + compile",
                  "torchdiffeq dopri5", "torchode tsit5")


# ----------------------------------------------------------------------------- training step


class StepProblem:
    """The training step of the module docstring, with one set of weights for every variant."""

    B, N, D, T = 128, 3, 3, 51

    def __init__(self, seed: int = 0):
        gen = torch.Generator().manual_seed(seed)
        torch.manual_seed(seed)
        self.model = MPNODE(self.D)
        self.adj = (torch.ones(self.N, self.N) - torch.eye(self.N)).expand(self.B, -1, -1)
        self.x0 = torch.randn(self.B, self.N, self.D, generator=gen)
        self.ts = torch.linspace(0.0, 2.5, self.T, dtype=torch.float64)
        self.target = torch.randn(self.B, self.T, self.N, self.D, generator=gen)
        # One SolverOptions per variant, as a training run has: the compiled variant's
        # steps share its compiled step.
        self.solvers = {name: TrainConfig(dataset="-", **options).solver
                        for name, (options, _) in VARIANTS.items()}

    def states(self, name: str) -> tuple[torch.Tensor, int]:
        """`[B, T, N, D]` predicted states and the RHS evaluations (max over samples)."""
        solver, integrate = self.solvers[name], VARIANTS[name][1]
        with integrator(integrate):
            out = self.model.rollout(self.x0, self.ts, self.adj, solver=solver)
        return out.states, out.n_f_evals

    def step(self, name: str) -> int:
        self.model.zero_grad(set_to_none=True)
        states, evals = self.states(name)
        torch.nn.functional.mse_loss(states, self.target).backward()
        return evals

    def chain(self, evals: int) -> None:
        """`evals` RHS evaluations forward and backward, chained by Euler updates (no solver)."""
        self.model.zero_grad(set_to_none=True)
        f = self.model.vector_field(self.adj)
        z = torch.cat([self.x0, self.x0.new_zeros(self.B, self.N, self.model.message_dim)], -1)
        t = torch.zeros(self.B, dtype=torch.float64)
        for _ in range(evals):
            z = z + 0.01 * f(t, z)
        z[..., : self.D].square().mean().backward()

    def max_error(self, name: str) -> float:
        """Max |state error| against a float64 solve of the same weights at rtol = atol = 1e-10."""
        with torch.no_grad():
            states, _ = self.states(name)
            model64 = MPNODE(self.D)
            model64.load_state_dict(self.model.state_dict())
            model64.double()
            ref = model64.rollout(self.x0.double(), self.ts, self.adj.double(),
                                  solver=SolverOptions(rtol=1e-10, atol=1e-10)).states
        return float((states.double() - ref).abs().max())


def _timed(fn) -> float:
    t0 = time.perf_counter()
    fn()
    return time.perf_counter() - t0


@contextlib.contextmanager
def busy_process():
    """One CPU-bound process beside the benchmark for as long as the block runs."""
    proc = subprocess.Popen([sys.executable, "-c", "while True: pass"])
    try:
        time.sleep(0.5)
        yield
    finally:
        proc.kill()
        proc.wait()


def bench_step(args) -> dict:
    problem = StepProblem()
    names = [n for n in STEP_VARIANTS if n in args.variants]
    evals, compile_s = {}, None
    for name in names:  # warm up; the first compiled call compiles
        seconds = _timed(lambda n=name: evals.__setitem__(n, problem.step(n)))
        if name == "mpnode tsit5 + compile":
            compile_s = seconds
        for _ in range(2):
            problem.step(name)
    times = {n: [] for n in names}
    base = names[0]
    ratios = {n: [] for n in names}
    chain = []
    for _ in range(args.rounds):
        for name in names:
            times[name].append(statistics.median(
                _timed(lambda n=name: problem.step(n)) for _ in range(args.repeats)))
        chain.append(statistics.median(
            _timed(lambda: problem.chain(evals[base])) for _ in range(args.repeats)))
        for name in names:
            ratios[name].append(times[name][-1] / times[base][-1])
    with busy_process():
        busy = [statistics.median(_timed(lambda: problem.step(base))
                                  for _ in range(args.repeats)) for _ in range(args.rounds)]
    chain_ms = 1e3 * statistics.median(chain)
    rows = [{"variant": n, "ms": 1e3 * statistics.median(times[n]),
             "ratio": statistics.median(ratios[n]), "evals": evals[n],
             "max_error": problem.max_error(n),
             "solver_share": solver_share(1e3 * statistics.median(times[n]),
                                          chain_ms * evals[n] / evals[base])} for n in names]
    return {"rows": rows, "chain_ms": chain_ms, "chain_evals": evals[base],
            "busy_ms": 1e3 * statistics.median(busy), "compile_s": compile_s}


def solver_share(step_ms: float, floor_ms: float) -> float:
    """The integrator's own share of a step: (step − floor) / step."""
    return (step_ms - floor_ms) / step_ms


# ----------------------------------------------------------------------------- epochs


@contextlib.contextmanager
def integrator(integrate):
    """MPNODE integrating with `integrate` (None: ours, the rollout it inherits)."""
    if integrate is None:
        yield
        return
    MPNODE.rollout = _peer_rollout(integrate)
    try:
        yield
    finally:
        del MPNODE.rollout  # back to the inherited `NeuralODEModel.rollout`


def run_variant(name, dataset, root, args):
    options, integrate = VARIANTS[name]
    # The whole horizon every epoch (Lorenz recommends the curriculum, whose growing horizon
    # would make epochs unequal and recompile the compiled variant at every length).
    config = TrainConfig(dataset=dataset, epochs=args.epochs, run_dir=root / name.replace(" ", "_"),
                         plots=False, device=args.device, trajectories=args.trajectories,
                         horizon_curriculum=False, **options)
    with integrator(integrate):
        summary = train(config)
    resolved = read_config(config.run_dir)
    rows = [r for r in read_metrics(config.run_dir) if r["epoch"] > 0]
    data = TrajectoryData.load(dataset)
    n_train = min(args.trajectories or len(data), len(data.subset("train")))
    batches = -(-n_train // resolved.batch_size)
    # The referee: the last weights, validated by our solver at tight tolerances.
    ckpt = load_checkpoint(checkpoint_path(config.run_dir, "last"))
    data = data.subset("validation")
    referee = evaluate(ckpt.build_model().to(args.device), data, ckpt.build_normalizer(),
                       solver=SolverOptions(rtol=1e-6, atol=1e-6), device=args.device)
    return {
        "variant": name,
        "s_per_epoch": statistics.median(r["train_seconds"] for r in rows[1:] or rows),
        "first_epoch_s": rows[0]["train_seconds"],
        "evals_per_batch": statistics.mean(r["rhs_evals"] for r in rows) / batches,
        "val_loss": rows[-1]["val_mse"],
        "referee_val_loss": referee.mse,
        "skipped": summary.skipped_batches,
        "config": resolved,
    }


def bench_epochs(args, root: Path) -> list[dict]:
    dataset = args.dataset or generate(
        GenerateConfig(**get_preset("lorenz3"), out=root / "lorenz3.h5")).path
    results = []
    for name in [n for n in EPOCH_VARIANTS if n in args.variants]:
        results.append(run_variant(name, dataset, root, args))
        r = results[-1]
        print(f"{name:30s} {r['s_per_epoch']:.3f} s/epoch  {r['evals_per_batch']:.0f} "
              f"evals/batch  val {r['val_loss']:.4g}  referee {r['referee_val_loss']:.4g}",
              file=sys.stderr)
    return results


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--part", choices=("all", "step", "epochs"), default="all")
    parser.add_argument("--epochs", type=int, default=30)
    parser.add_argument("--rounds", type=int, default=7, help="interleaved rounds (step)")
    parser.add_argument("--repeats", type=int, default=3, help="steps per variant per round")
    parser.add_argument("--variants", nargs="+", default=list(VARIANTS), choices=VARIANTS)
    parser.add_argument("--dataset", type=Path, help="lorenz3 dataset (default: generate it)")
    parser.add_argument("--trajectories", type=int, help="train on the first K only (smoke)")
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--out", type=Path, default=RESULTS)
    args = parser.parse_args(argv)
    torch.set_num_threads(args.threads)
    load_before = os.getloadavg()
    step = epochs = None
    if args.part in ("all", "step"):
        step = bench_step(args)
        for r in step["rows"]:
            print(f"{r['variant']:30s} {r['ms']:.1f} ms  × ours {r['ratio']:.2f}  "
                  f"{r['evals']} evals  max error {r['max_error']:.1e}  "
                  f"solver share {r['solver_share']:.0%}", file=sys.stderr)
        print(f"{'RHS floor':30s} {step['chain_ms']:.1f} ms  {step['chain_evals']} evals",
              file=sys.stderr)
    if args.part in ("all", "epochs"):
        with tempfile.TemporaryDirectory() as tmp:
            epochs = bench_epochs(args, Path(tmp))
    write_report(args, step, epochs, load_before, os.getloadavg())
    return 0


def write_report(args, step, epochs, load_before, load_after) -> None:
    import torchdiffeq
    import torchode

    lines = [
        "# Training benchmark: MP-NODE's training step and epochs against torchdiffeq and "
        "torchode",
        "",
        f"Command: `bench/train.py {' '.join(sys.argv[1:])}`. Machine: {platform.machine()}, "
        f"{os.cpu_count()} cores, {args.threads} torch thread(s), device {args.device}, "
        f"torch {torch.__version__}, torchode {getattr(torchode, '__version__', '?')}, "
        f"torchdiffeq {torchdiffeq.__version__}, Python {sys.version.split()[0]}, "
        f"{time.strftime('%Y-%m-%dT%H:%M')}. Load average (1/5/15 min) before "
        f"{'/'.join(f'{x:.2f}' for x in load_before)}, after "
        f"{'/'.join(f'{x:.2f}' for x in load_after)}. "
        "`× ours` = time / mpnode tsit5's time in the same run (higher = slower than ours).",
        "",
    ]
    if step is not None:
        rows = step["rows"]
        lines += [
            "## Training step (forward + backward of one whole-horizon solve)",
            "",
            "MP-NODE (hidden 32, two tanh layers, M = 3), N = 3, D = 3, B = 128, 51 samples "
            "over 2.5 s, float32, rtol = atol = 1e-4, MSE; "
            f"median of {args.rounds} interleaved rounds × {args.repeats} steps. max error: "
            "the states' max |error| against the same weights solved in float64 at 1e-10. "
            "solver share: (step − floor) / step, the floor scaled to the row's RHS evaluations.",
            "",
            "| integrator | ms/step | × ours | RHS evals | max error | solver share |",
            "|---|---:|---:|---:|---:|---:|",
        ]
        for r in rows:
            lines.append(f"| {r['variant']} | {r['ms']:.1f} | {r['ratio']:.2f} | {r['evals']} | "
                         f"{r['max_error']:.1e} | {r['solver_share']:.0%} |")
        base = rows[0]["ms"]
        lines += [
            f"| RHS floor: {step['chain_evals']} evaluations chained, no solver | "
            f"{step['chain_ms']:.1f} | {step['chain_ms'] / base:.2f} | {step['chain_evals']} | – "
            "| – |",
            f"| mpnode tsit5 beside one busy process | {step['busy_ms']:.1f} | "
            f"{step['busy_ms'] / base:.2f} | – | – | – |",
            "",
        ]
        if step["compile_s"] is not None:
            lines += [f"The compiled variant's first step (compiling) took "
                      f"{step['compile_s']:.1f} s.", ""]
    if epochs:
        cfg = epochs[0]["config"]
        base = next((r for r in epochs if r["variant"] == "mpnode tsit5"), epochs[0])
        lines += [
            "## Training epochs: lorenz3",
            "",
            f"{args.epochs} epochs per variant from the same initial weights (seed "
            f"{cfg.seed}), the default recipe (batch {cfg.batch_size}, {cfg.loss} loss, lr "
            f"{cfg.lr:g}, the whole horizon every epoch), rtol = atol = 1e-4. s/epoch: median "
            "training time of an epoch after the first (validation excluded). val MSE: after "
            "the last epoch with the variant's own integrator; referee: the same weights "
            "solved by ours at 1e-6."
            + (f" Trained on the first {args.trajectories} trajectories only."
               if args.trajectories else ""),
            "",
            "| integrator | s/epoch | × ours | first epoch s | evals/batch | val MSE | referee "
            "val MSE | skipped batches |",
            "|---|---:|---:|---:|---:|---:|---:|---:|",
        ]
        for r in epochs:
            lines.append(
                f"| {r['variant']} | {r['s_per_epoch']:.3f} | "
                f"{r['s_per_epoch'] / base['s_per_epoch']:.2f} | {r['first_epoch_s']:.3f} | "
                f"{r['evals_per_batch']:.1f} | {r['val_loss']:.4g} | "
                f"{r['referee_val_loss']:.4g} | {r['skipped']} |")
        lines.append("")
    args.out.parent.mkdir(parents=True, exist_ok=True)
    tmp = args.out.with_suffix(".tmp")
    tmp.write_text("\n".join(lines))
    tmp.replace(args.out)
    print(f"wrote {args.out}", file=sys.stderr)


if __name__ == "__main__":
    sys.exit(main())
