"""Training benchmark: MP-NODE epochs on `lorenz3`, our solver against torchdiffeq and torchode.

Every variant trains the same model (MP-NODE, hidden 32, two tanh layers, M = 3, graph
"sys", seed 0) with the same code — `mpnode_cli.training.loop.train`, batch 128, Adam 1e-3,
Huber loss, clip 500, noise 1e-4 — on the train split of the `lorenz3` preset (1000
trajectories × 51 samples, 700 train). Only the integrator inside `MPNODE.rollout` differs:

- mpnode tsit5: our solver, adaptive, rtol = atol = 1e-4 (the default);
- mpnode tsit5 fixed: our solver with fixed steps of one sample interval (dt = 0.05);
- torchdiffeq dopri5: `torchdiffeq.odeint` at the same tolerances (one step size for the
  whole batch, as torchdiffeq does);
- torchode tsit5: `torchode` AutoDiffAdjoint + IntegralController at the same tolerances
  (per-sample steps, dense output at the sample times).

For the peers `MPNODE.rollout` is swapped for one that integrates `model.vector_field` with
that library (backpropagation through the solver's operations in every case). Reported per
variant: seconds per epoch of training (median over epochs after the first), forward RHS
evaluations per batch (max over samples), the validation loss after the last epoch with the
variant's own integrator, and the same weights' validation loss re-measured with our
adaptive solver at rtol = atol = 1e-6 (a common referee: a variant that integrates loosely
can look better than its model is).

Usage:
    .venv/bin/python bench/train.py                         # 100 epochs per variant
    .venv/bin/python bench/train.py --epochs 3 --trajectories 200 --out /tmp/train.md  # smoke
Writes `bench/results/train.md`. Target: ≥ 2× faster per epoch than torchdiffeq
and not slower than torchode, at equal loss.
"""

from __future__ import annotations

import argparse
import contextlib
import platform
import statistics
import sys
import tempfile
from pathlib import Path

import torch

from mpnode_cli.config import GenerateConfig, TrainConfig
from mpnode_cli.data.dataset import TrajectoryData
from mpnode_cli.data.generate import generate
from mpnode_cli.data.presets import get_preset
from mpnode_cli.models.base import Rollout
from mpnode_cli.models.mpnode import MPNODE
from mpnode_cli.solver.options import SolverOptions
from mpnode_cli.training.checkpoint import load_checkpoint
from mpnode_cli.training.evaluate import evaluate
from mpnode_cli.training.loop import train
from mpnode_cli.training.run import checkpoint_path, read_metrics

RESULTS = Path(__file__).parent / "results" / "train.md"


def _peer_rollout(integrate):
    """An `MPNODE.rollout` that integrates with `integrate(f, z0, ts, rtol, atol) -> (zs, evals)`.

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
    "mpnode tsit5 fixed dt=0.05": ({"solver": {"fixed_dt": 0.05}}, None),
    "torchdiffeq dopri5": ({}, torchdiffeq_dopri5),
    "torchode tsit5": ({}, torchode_tsit5),
}


@contextlib.contextmanager
def integrator(integrate):
    original = MPNODE.rollout
    if integrate is not None:
        MPNODE.rollout = _peer_rollout(integrate)
    try:
        yield
    finally:
        MPNODE.rollout = original


def run_variant(name, dataset, root, args):
    options, integrate = VARIANTS[name]
    config = TrainConfig(dataset=dataset, epochs=args.epochs, run_dir=root / name.replace(" ", "_"),
                         plots=False, device=args.device, trajectories=args.trajectories,
                         **options)
    with integrator(integrate):
        summary = train(config)
    rows = [r for r in read_metrics(config.run_dir) if r["epoch"] > 0]
    data = TrajectoryData.load(dataset)
    n_train = min(args.trajectories or len(data), len(data.subset("train")))
    batches = -(-n_train // config.batch_size)
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
        "val_loss": rows[-1]["val_loss"],
        "referee_val_loss": referee.huber,
        "skipped": summary.skipped_batches,
    }


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--epochs", type=int, default=100)
    parser.add_argument("--variants", nargs="+", default=list(VARIANTS), choices=VARIANTS)
    parser.add_argument("--dataset", type=Path, help="lorenz3 dataset (default: generate it)")
    parser.add_argument("--trajectories", type=int, help="train on the first K only (smoke)")
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--out", type=Path, default=RESULTS)
    args = parser.parse_args(argv)
    torch.set_num_threads(args.threads)

    with tempfile.TemporaryDirectory() as tmp:
        root = Path(tmp)
        dataset = args.dataset or generate(
            GenerateConfig(**get_preset("lorenz3"), out=root / "lorenz3.h5")).path
        results = []
        for name in args.variants:
            results.append(run_variant(name, dataset, root, args))
            r = results[-1]
            print(f"{name:28s} {r['s_per_epoch']:.3f} s/epoch  {r['evals_per_batch']:.0f} "
                  f"evals/batch  val {r['val_loss']:.4g}  referee {r['referee_val_loss']:.4g}",
                  file=sys.stderr)
    write_report(args, results)
    return 0


def write_report(args, results) -> None:
    import torchdiffeq
    import torchode

    base = next((r for r in results if r["variant"] == "mpnode tsit5"), results[0])
    lines = [
        "# Training benchmark: MP-NODE on lorenz3 (700 train trajectories × 51 samples)",
        "",
        f"Machine: {platform.machine()}, {args.threads} threads, device {args.device}, "
        f"torch {torch.__version__}, torchode {getattr(torchode, '__version__', '?')}, "
        f"torchdiffeq {torchdiffeq.__version__}, Python {sys.version.split()[0]}. "
        f"{args.epochs} epochs per variant from the same initial weights (seed 0), batch 128, "
        "Adam 1e-3, Huber loss; rtol = atol = 1e-4. s/epoch: median training time of an "
        "epoch after the first (validation excluded). evals/batch: forward RHS evaluations "
        "(max over samples). val: validation Huber loss after the last epoch with the "
        "variant's own integrator; referee: the same weights with our solver at 1e-6."
        + (f" Trained on the first {args.trajectories} trajectories only."
           if args.trajectories else ""),
        "",
        "| integrator | s/epoch | × ours | first epoch s | evals/batch | val loss | referee "
        "val loss | skipped batches |",
        "|---|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for r in results:
        lines.append(
            f"| {r['variant']} | {r['s_per_epoch']:.3f} | "
            f"{r['s_per_epoch'] / base['s_per_epoch']:.2f} | {r['first_epoch_s']:.3f} | "
            f"{r['evals_per_batch']:.1f} | {r['val_loss']:.4g} | {r['referee_val_loss']:.4g} | "
            f"{r['skipped']} |")
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text("\n".join(lines) + "\n")
    print(f"wrote {args.out}", file=sys.stderr)


if __name__ == "__main__":
    sys.exit(main())
