"""One optimizer step of a model or an ensemble's members: `train_step`.

Every process of a torchrun launch takes the same decision for each member: its failed
solves, non-finite losses and batch loss are summed over the ranks before a step is taken
or skipped, and the gradients are the global batch's (`mpnode_cli.training.distributed`).
A member's bad batch leaves its weights and Adam moments as they are; the others update.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import NamedTuple

import torch

from mpnode_cli.config.train import TrainConfig
from mpnode_cli.solver import Status
from mpnode_cli.training import distributed


class StepResult(NamedTuple):
    """One member's optimizer step: the global batch's loss, the gradient norm, this
    rank's RHS evaluations, and why the step was skipped (None: it was taken)."""

    loss: float
    grad_norm: float
    n_f_evals: int
    skip: str | None


def train_step(model, optimizer, inputs: list, ts: torch.Tensor, graphs: list, loss_fn,
               config: TrainConfig, world: distributed.World, active: Sequence[int] = (0,),
               share: float = 1.0) -> list[StepResult]:
    """One update of each active member of `model` (one model: its one member, itself)
    from its own `(x: [B_r, H, N, D], u)` in `inputs` and its graphs, the fraction
    `share` = B_r / B of the global batch. A member's bad batch (failed solves, non-finite
    loss or gradient) leaves its weights and moments as they are; the others update.

    Returns each active member's `StepResult`.
    """
    members = model.members
    optimizer.zero_grad(set_to_none=True)
    batches = (_losses(model, inputs, ts, graphs, loss_fn, active, config.solver)
               if len(inputs[0][0]) else None)
    # Summed over ranks, so that every rank takes the same decision: failed solves per
    # status, non-finite losses, and the batch's mean loss (each rank's weighted by share).
    verdict = torch.zeros(len(active), len(Status) + 2, dtype=torch.float64)
    for j, batch in enumerate(batches or []):
        value = None if batch.loss is None else batch.loss.item()
        if value is not None and not math.isfinite(value):
            verdict[j, -2] = 1
        elif value is not None:
            verdict[j, -1] = value * share
        else:
            verdict[j, :len(Status)] = torch.bincount(batch.status.cpu(), minlength=len(Status))
    verdict = world.sum(verdict)
    reasons = [_skip_reason(v) for v in verdict]
    good = [b.loss for b, r in zip(batches or [], reasons, strict=False)
            if r is None and b.loss is not None]
    if good:
        sum(good).backward()
    for j, k in enumerate(active):
        if reasons[j] is not None:  # a stacked solve gives a skipped member zeros: none
            members[k].zero_grad(set_to_none=True)
    world.sum_gradients(list(model.parameters()), share)  # the global batch's gradient
    out = []
    for j, k in enumerate(active):
        evals = batches[j].n_f_evals if batches else 0
        if reasons[j] is not None:
            out.append(StepResult(math.nan, math.nan, evals, reasons[j]))
            continue
        norm = float(torch.nn.utils.clip_grad_norm_(members[k].parameters(), config.clip))
        if not math.isfinite(norm):
            members[k].zero_grad(set_to_none=True)
            out.append(StepResult(math.nan, norm, evals, "non-finite gradient"))
            continue
        out.append(StepResult(float(verdict[j, -1]), norm, evals, None))
    optimizer.step()
    return out


def _losses(model, inputs: list, ts: torch.Tensor, graphs: list, loss_fn,
            active: Sequence[int], solver) -> list:
    """Each active member's `BatchLoss` on its own batch (an ensemble's in one solve)."""
    xs = torch.stack([x for x, _ in inputs])  # (S', B_r, H, N, D)
    us = None if inputs[0][1] is None else torch.stack([u for _, u in inputs])
    return model.training_losses(xs, ts, graphs, us, loss_fn, active, solver=solver)


def _skip_reason(verdict: torch.Tensor) -> str | None:
    """Why a member's step is skipped, from its summed verdict; None: it is good."""
    failed = int(verdict[1:len(Status)].sum())
    if failed:
        worst = Status(int(verdict[:len(Status)].nonzero().max())).name
        return f"solver {worst} on {failed} trajectories"
    if verdict[-2] > 0:
        return "non-finite loss"
    return None
