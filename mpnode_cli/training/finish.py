"""The end of a training run: its best checkpoint scored on the test split (of each
dataset that has one, and pooled), the plots, and `summary.json`."""

from __future__ import annotations

from dataclasses import asdict
from typing import Any

from mpnode_cli.data.dataset import SPLITS
from mpnode_cli.report.members import shown
from mpnode_cli.training import run as runs
from mpnode_cli.training.checkpoint import Checkpoint, load_checkpoint
from mpnode_cli.training.checkpoint_report import evaluate_datasets
from mpnode_cli.training.run_state import Run


def finish(run: Run) -> runs.TrainSummary:
    """The best checkpoint on the test split (of each dataset that has one; pooled), its
    plots, and `summary.json`."""
    config, state, data = run.config, run.state, run.datas[0]
    best = load_checkpoint(runs.checkpoint_path(run.run_dir, "best"))
    run.emit({"event": "test"})
    test = None
    if any(bool((d.split == SPLITS["test"]).any()) for d in run.datas):
        test = evaluate_datasets(best, run.datas, run.names, split="test", verb="test",
                                 batch_size=config.val_batch_size, device=run.device,
                                 plot_dir=run.run_dir / "plots" if config.plots else None)
    members = state.members
    best_epoch = max(m.best_epoch for m in members)
    min_val = sum(m.best_val for m in members) / len(members)
    summary = runs.TrainSummary(
        run_dir=str(run.run_dir), model=run.kind, model_config=run.model_config,
        parameters=count_parameters(run.model), dataset=str(config.datasets[0]),
        dataset_fingerprint=data.fingerprint, system=data.system,
        num_nodes=data.num_nodes, loss=config.loss, epochs=state.epoch,
        best_epoch=best_epoch, min_val_loss=min_val,
        min_val_mse=best.metrics.get("val_mse"), table2=best_epoch * min_val,
        test=test and test["result"], wall_seconds=state.seconds,
        baselines=test and test["baselines"],
        seconds_per_epoch=runs.seconds_per_epoch(run.run_dir), skipped_batches=state.skipped,
        restores=state.restores,
        init_checkpoint=None if config.init_checkpoint is None else str(config.init_checkpoint),
        parent_sha256=run.parent_sha, world_size=run.world.size,
        by_dataset=_summary_by_dataset(run.names, run.facts, best, test),
        stopped_early=state.epoch if state.epoch < config.epochs else None,
        members=shown(len(members), _summary_members(run, test)),
    )  # fmt: skip
    runs.write_json(run.run_dir / runs.SUMMARY, asdict(summary))
    return summary


def _summary_members(run: Run, test: dict[str, Any] | None) -> list[dict[str, Any]]:
    """summary.json's `members`: each member's seed, best epoch, best validation loss, the
    epoch it stopped early (0: it did not) and test metrics (None without a test split)."""
    tested = ((test or {}).get("result") or {}).get("members") or []
    return [{"member": k, "seed": run.config.seed + k, "best_epoch": m.best_epoch,
             "min_val_loss": m.best_val, "stopped": m.stopped,
             "test": tested[k] if k < len(tested) else None}
            for k, m in enumerate(run.state.members)]


def _summary_by_dataset(names: list[str], facts: dict[str, Any], best: Checkpoint,
                        test: dict[str, Any] | None) -> dict[str, Any] | None:
    """summary.json's `by_dataset` (None for one dataset): each dataset's path, fingerprint,
    N, validation MSE at the best epoch, and test metrics and baselines (None without a
    test split)."""
    records = facts.get("datasets")
    if not records:
        return None
    val = best.metrics.get("val_mse_by_dataset") or {}
    tested = (test or {}).get("by_dataset") or {}
    return {name: {"path": r["path"], "fingerprint": r["fingerprint"],
                   "num_nodes": r["num_nodes"], "val_mse": val.get(name),
                   "test": (tested.get(name) or {}).get("result"),
                   "baselines": (tested.get(name) or {}).get("baselines")}
            for name, r in zip(names, records, strict=True)}


def count_parameters(model) -> int:
    """The model's trainable parameters."""
    return sum(p.numel() for p in model.parameters() if p.requires_grad)
