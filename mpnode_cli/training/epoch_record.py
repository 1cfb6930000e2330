"""The end of a training epoch: the validation result, each member's best epoch, its next
lr and early stop, and the epoch's metrics row (`validate`, `record`).

The validation loss that selects the best epoch is the pooled one over the datasets
(`mpnode_cli.training.eval_result.pooled`); an ensemble's members are each judged on their
own result, and its row holds their mean ± std beside each member's row.
"""

from __future__ import annotations

from typing import Any

import torch

from mpnode_cli.report.members import shown
from mpnode_cli.training.eval_result import EvalResult, by_dataset, pooled
from mpnode_cli.training.evaluate import evaluate
from mpnode_cli.training.losses import run_angles
from mpnode_cli.training.lr_schedule import LRSchedule
from mpnode_cli.training.run_state import Run


def validate(run: Run) -> tuple[EvalResult, list[EvalResult]]:
    """The pooled validation result (the loss that selects the best epoch) and each
    dataset's; each rank rolls out its part, and the error sums are added over ranks."""
    world = run.world
    angles = run_angles(run.config.wrap_angles, run.facts, run.normalizer.x_std)
    each = [evaluate(run.model, part, run.normalizer, batch_size=run.config.val_batch_size,
                     solver=run.config.solver, device=run.device, angles=angles,
                     combine=world.sum if world.size > 1 else None) for part in run.val_parts]
    return pooled(each, [d.num_nodes for d in run.datas], run.loss_scale), each


def record(run: Run, schedules: list[LRSchedule], epoch: int, val: EvalResult,
           each: list[EvalResult], steps: dict | None, seconds: float) -> dict[str, Any]:
    """Update each member's best epoch from the validation result, set its next epoch's lr
    and stop it early where `stop_patience` says; return the metrics row (`lr`: the one
    this epoch ran at; an ensemble's: the members' mean, each member's under `members`)."""
    config, state = run.config, run.state
    results = val.members or [val]
    lrs, improved = [s.lr for s in schedules], []
    for k, (member, schedule, result) in enumerate(zip(state.members, schedules, results,
                                                       strict=True)):
        if member.stopped:
            continue
        loss = result.loss(config.loss)
        if loss < member.best_val:
            member.best_val, member.best_epoch = loss, epoch
            improved.append(k)
        schedule.end_epoch(epoch, k in improved)
        if config.stop_patience and epoch - member.best_epoch >= config.stop_patience:
            member.stopped = epoch
    state.seconds += seconds
    steps = steps or {"train_loss": None, "horizon": None, "grad_norm": None,
                      "rhs_evals": 0, "skipped": 0, "skip_reasons": [], "train_seconds": 0.0}
    by_member = steps.pop("by_member", {})
    row = {"epoch": epoch, **steps, "val_loss": val.loss(config.loss), "val_mse": val.mse,
           "val_failed": val.failed, "val_rhs_evals": val.n_f_evals, "lr": lrs[0],
           "seconds": seconds, "improved": bool(improved),
           "backprop_checkpoints": config.solver.checkpoints} | by_dataset(
               run.names, each, config.loss)
    return row | (shown(len(results), _member_rows(run, val, results, lrs, improved,
                                                    by_member)) or {})


def _member_rows(run: Run, val: EvalResult, results: list[EvalResult], lrs: list[float],
                 improved: list[int], by_member: dict[int, dict]) -> dict[str, Any]:
    """An ensemble's metrics: the members' mean ± std (population) of the validation loss
    and MSE, the members' mean prediction's MSE, each member's row, and who improved."""
    config = run.config
    losses = torch.tensor([r.loss(config.loss) for r in results], dtype=torch.float64)
    mses = torch.tensor([r.mse for r in results], dtype=torch.float64)
    members = [{"member": k, "seed": config.seed + k, "val_loss": float(losses[k]),
                "val_mse": float(mses[k]), "lr": lrs[k], "improved": k in improved,
                "best_epoch": m.best_epoch, "stopped": m.stopped, **by_member.get(k, {})}
               for k, m in enumerate(run.state.members)]
    return {"val_loss": float(losses.mean()), "val_loss_std": float(losses.std(correction=0)),
            "val_mse": float(mses.mean()), "val_mse_std": float(mses.std(correction=0)),
            "ensemble_val_mse": val.mse, "lr": sum(lrs) / len(lrs), "members": members,
            "improved_members": improved}
