"""Rollout errors of a model on a dataset split: the numbers `train`, `evaluate` and `zeroshot`
report.

Every trajectory is predicted open-loop from its first sample over the whole horizon (single
shooting, as the model is trained) and compared with the data at every later sample time
(t₀ is given, so it is excluded). Errors are taken in the training normalization — the
paper's "test error" is an MSE in normalized units — and per state in physical units.

Every MSE comes with two naive predictors in the same units (`baseline_mse`), so that a
number can be read without knowing the system: "hold x(0)" (nothing moves) and "time mean"
(the train split's average trajectory, which knows the typical evolution but not this
trajectory). A model worth having beats both by a wide margin. A checkpoint's report, the
baselines beside its errors, is `mpnode_cli.training.checkpoint_report`'s.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import dataclass

import torch

from mpnode_cli.data.dataset import Normalizer, TrajectoryData
from mpnode_cli.data.stream import StreamedTrajectories, prefetched
from mpnode_cli.models.base import NeuralModel, model_dtype
from mpnode_cli.models.ensemble import spread_error_correlation
from mpnode_cli.progress import Progress
from mpnode_cli.report.members import shown
from mpnode_cli.solver.options import SolverOptions
from mpnode_cli.training.baselines import baseline_mse  # noqa: F401  (evaluate's own)
from mpnode_cli.training.eval_result import EvalResult
from mpnode_cli.training.losses import Angles, difference, huber_loss, node_mse_loss


@dataclass
class Prediction:
    """Physical-unit trajectories of a few samples, for plots.

    Attributes:
        time: `[T]` float64. true, pred: `[B, T, N, D]`. messages: `[B, T, N, M]` or None.
        status: `[B]` solver status per trajectory.
        spread: `[B, T, N, D]` an ensemble's members' std (physical units), or None.
    """

    time: torch.Tensor
    true: torch.Tensor
    pred: torch.Tensor
    messages: torch.Tensor | None
    status: torch.Tensor
    spread: torch.Tensor | None = None


class _Sums:
    """The error sums of one predictor over the batches, and the `EvalResult` they give."""

    def __init__(self, t: int, d: int):
        self.sq_time = torch.zeros(t, dtype=torch.float64)  # Σ squared error per sample time
        self.sq_phys = torch.zeros(d, dtype=torch.float64)  # Σ squared physical error per state
        self.huber, self.node_mse, self.ok, self.failed = 0.0, 0.0, 0, 0

    def add(self, pred: torch.Tensor, x: torch.Tensor, good: torch.Tensor,
            normalizer: Normalizer, angles: Angles | None = None) -> None:
        """One batch: `pred, x: [B, T, N, D]` normalized, `good: [B]` bool (CPU); `angles`:
        components compared mod 2π (`mpnode_cli.training.losses.difference`)."""
        self.failed += int((~good).sum())
        if not good.any():
            return
        pred, x = pred[good.to(pred.device)], x[good.to(x.device)]
        self.ok += len(pred)
        self.sq_time += difference(pred, x, angles).pow(2).double().sum(dim=(0, 2, 3)).cpu()
        self.huber += float(huber_loss(pred, x, angles=angles).double()) * len(pred)
        self.node_mse += float(node_mse_loss(pred, x, angles=angles).double()) * len(pred)
        phys_err = difference(normalizer.denorm_x(pred), normalizer.denorm_x(x),
                              None if angles is None else angles.physical())
        self.sq_phys += phys_err[:, 1:].pow(2).double().sum(dim=(0, 1, 2)).cpu()

    def combined(self, combine: Callable[[torch.Tensor], torch.Tensor] | None) -> None:
        """Add the sums of every process's part (`combine`: an all-reduce)."""
        if combine is None:
            return
        t = self.sq_time.numel()
        sums = combine(torch.cat([torch.tensor([self.ok, self.failed, self.huber,
                                                self.node_mse], dtype=torch.float64),
                                  self.sq_time, self.sq_phys]))
        self.ok, self.failed = int(sums[0]), int(sums[1])
        self.huber, self.node_mse = float(sums[2]), float(sums[3])
        self.sq_time, self.sq_phys = sums[4:4 + t], sums[4 + t:]

    def result(self, k: int, n: int, n_f_evals: int, seconds: float) -> EvalResult:
        """The errors over K trajectories of N nodes."""
        ok, t, d = self.ok, self.sq_time.numel(), self.sq_phys.numel()
        per_time = self.sq_time / max(ok * n * d, 1) if ok else torch.full((t,), math.nan)
        predicted = max(ok * (t - 1) * n, 1)
        return EvalResult(
            trajectories=k, failed=self.failed,
            mse=float(self.sq_time[1:].sum() / (predicted * d)) if ok and t > 1 else math.nan,
            huber=self.huber / ok if ok else math.nan,
            node_mse=self.node_mse / ok if ok else math.nan,
            rmse=(self.sq_phys / predicted).sqrt().tolist() if ok else [math.nan] * d,
            mse_vs_time=per_time.tolist(), n_f_evals=n_f_evals, seconds=seconds)


def evaluate(model: NeuralModel, data: TrajectoryData | StreamedTrajectories,
             normalizer: Normalizer, *,
             batch_size: int = 128, solver: SolverOptions | None = None,
             device: str | torch.device = "cpu",
             combine: Callable[[torch.Tensor], torch.Tensor] | None = None,
             progress: Progress | None = None, angles: Angles | None = None,
             per_batch: Callable[..., None] | None = None) -> EvalResult:
    """Roll `model` out on every trajectory of `data` and measure its errors.

    Args:
        model: the model, already on `device`; an ensemble (`mpnode_cli.models.ensemble`)
            is scored on its members' mean, with each member's errors and the spread.
        data: the trajectories (one split, or all); physical units; in memory or read
            batch by batch (`StreamedTrajectories`).
        normalizer: the training normalization (the model works in its units).
        batch_size: trajectories per rollout.
        solver: how the rollouts are integrated, normally as the model was trained
            (None: `solve`'s defaults).
        device: where the rollouts run.
        combine: when `data` is one part of a split that several processes share, adds
            the error sums of all parts (`[S]` float64 → `[S]`, e.g. an all-reduce), so
            that the result is the whole split's; RHS evaluations are then the parts' sum.
        progress: called after each batch with the trajectories rolled out and K.
        angles: state components whose errors are taken mod 2π (`run_angles`; None:
            plain differences).
        per_batch: called with each batch, its normalized states, rollout and `good`
            mask (`mpnode_cli.training.by_degree.DegreeSums.add`).

    Returns:
        An `EvalResult`; errors are NaN when every rollout failed (or `data` is empty).
    """
    start = time.perf_counter()
    k, t, d = len(data), data.time.numel(), data.node_dim
    batch_size = data.graphs.rollout_batch(batch_size)
    ts = data.time.to(device)
    sums, members = _Sums(t, d), [_Sums(t, d) for _ in model.members]
    spreads, errors = [torch.zeros(0)], [torch.zeros(0)]  # [K] each, with no batch too
    n_f_evals, done = 0, 0
    was_training = model.training
    model.eval()
    with torch.no_grad(), prefetched(data, torch.arange(k).split(batch_size)) as batches:
        for batch in batches:
            x, u = _normalized(batch, normalizer, device, model)  # (B,T,N,D), (B,T,N,U)
            out = model.rollout_from_data(x, ts, batch.graph(device), u, solver=solver)
            n_f_evals += out.n_f_evals
            done += len(x)
            if progress is not None:
                progress(done, k)
            good = (out.status == 0).cpu() & torch.isfinite(out.states).flatten(1).all(1).cpu()
            sums.add(out.states, x, good, normalizer, angles)
            if per_batch is not None:
                per_batch(batch, x, out, good)
            for sum_k, pred_k, status_k in zip(members, out.members, out.member_status,
                                               strict=True):
                ok_k = (status_k == 0).cpu() & torch.isfinite(pred_k).flatten(1).all(1).cpu()
                sum_k.add(pred_k, x, ok_k, normalizer, angles)
            spreads.append(out.spread[:, 1:].flatten(1).mean(1)[good.to(x.device)].cpu())
            errors.append(difference(out.states, x, angles)[:, 1:].pow(2).flatten(1).mean(1).sqrt()[
                good.to(x.device)].cpu())
    model.train(was_training)
    sums.combined(combine)
    seconds, n = time.perf_counter() - start, data.num_nodes
    if combine is not None:
        k, n_f_evals = (int(v) for v in combine(torch.tensor([k, n_f_evals],
                                                             dtype=torch.float64)).tolist())
    result = sums.result(k, n, n_f_evals, seconds)
    for sum_k in members:
        sum_k.combined(combine)
    spread, error = torch.cat(spreads), torch.cat(errors)
    # Every member's numbers, shown for an ensemble (a single model is its one member).
    s = len(members)
    result.members = shown(s, [m.result(k, n, n_f_evals, seconds) for m in members])
    result.spread = shown(s, float(spread.mean()) if spread.numel() else math.nan)
    result.spread_error_corr = shown(s, spread_error_correlation(spread, error))
    return result


def predict(model: NeuralModel, data: TrajectoryData, normalizer: Normalizer,
            index: torch.Tensor, *, solver: SolverOptions | None = None,
            device: str | torch.device = "cpu") -> Prediction:
    """Roll out the trajectories at `index` (`[B]`) and return them in physical units (an
    ensemble's: the members' mean, with their spread)."""
    batch = data.take(index)
    x, u = _normalized(batch, normalizer, device, model)
    with torch.no_grad():
        out = model.rollout_from_data(x, data.time.to(device), batch.graph(device), u,
                                      solver=solver, return_messages=True)
    messages = None if out.messages is None else out.messages.cpu()
    spread = shown(len(model.members), normalizer.denorm_spread(out.spread).cpu())
    return Prediction(time=data.time, true=batch.states, pred=normalizer.denorm_x(out.states).cpu(),
                      messages=messages, status=out.status.cpu(), spread=spread)


def _normalized(batch: TrajectoryData, normalizer: Normalizer, device, model=None):
    """The batch's states and controls normalized on `device`, in `model`'s precision."""
    dtype = model_dtype(model)
    x = normalizer.norm_x(batch.states.to(device)).to(dtype)
    u = None if batch.controls is None else normalizer.norm_u(
        batch.controls.to(device)).to(dtype)
    return x, u
