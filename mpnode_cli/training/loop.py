"""Training and finetuning, top to bottom: `train(config) -> TrainSummary`.

The loop is the authors' (MPNODE.jl, exps/train_pipeline.jl and src/learn.jl): z-scored
data, whole-horizon single shooting from x(t₀), Adam with global-norm clipping, 1e-4
Gaussian noise on the normalized training data, the best-validation weights kept. Its
choices (loss, batches, lr schedule, curriculum, aggregation) come from a recipe
(`mpnode_cli.training.recipe`): mpnode's measured one by default, the paper's exact one on
request. Departures from the authors in every recipe: normalization is fitted on the train
split only; the validation loss is a mean over trajectories (not over batches); a separate
test split is reported at the end.

A run is five stages, each a named piece:
1. the run setup (`mpnode_cli.training.setup`): data, model, normalizer, optimizer and a
   resumed run's state, in a `Run`;
2. the learning rate, one policy (`mpnode_cli.training.schedule.LRSchedule`);
3. the checkpointer (`mpnode_cli.training.checkpointer.Checkpointer`): each epoch's files,
   all or none, and the snapshot a rollback and an interrupt go back to;
4. the epochs: `_train_epoch` (one pass of optimizer steps, `_step`), validation, `_record`;
5. the best checkpoint on the test split, and `summary.json` (`_finish`).

Finetuning is this same function started from another point: `config.init_checkpoint`
supplies the weights and the architecture (and, unless `renormalize`, the normalization);
the optimizer is fresh. Resuming (`resume=True`) restores a run's `last.pt` — weights,
optimizer, RNG states and the loop's counters — so 2 + 2 epochs equal 4
(`mpnode_cli.training.resume` says what may change).

Several datasets (`config.dataset` a list: one system, any N) are trained on at once
(`mpnode_cli.data.pooled`): each batch is one dataset's, the batches of all of them are
interleaved in a seeded order, the normalization and the model's statistics are fitted on
the train splits pooled, and validation and test are each dataset's and pooled (an
element-weighted mean, `mpnode_cli.training.evaluate.pooled`), the pooled validation loss
choosing the best epoch. One dataset runs exactly as it did before several were possible.

With `config.stream` the data stay in the file (`mpnode_cli.data.stream`): the batches are
the same, read by a background thread as the epoch goes, and the normalization is fitted
in a pass over the file, so the losses are those of the in-memory run.

Under torchrun the processes train one model data-parallel (`mpnode_cli.training.distributed`):
each takes its slice of every global batch, the update is one process's update of that
batch, and rank 0 alone writes the run folder and reports progress. The run folder holds
nothing that depends on the number of processes, so a run resumes with any number.

`progress`, if given, is called with one dict per event, `event` naming it:
`start` (run_dir, first_epoch, epochs, batches), `batch` (epoch, batch, batches, loss),
`skip` (epoch, batch, reason), `restore` (epoch, lr), `epoch` (the metrics row), `test`,
and `warning` (text: something the user asked for that the run does otherwise, e.g. more
`trajectories` than a train split holds).
"""

from __future__ import annotations

import copy
import math
import os
import shutil
import time
from dataclasses import asdict
from pathlib import Path
from typing import Any

import torch

from mpnode_cli.config import TrainConfig
from mpnode_cli.data.dataset import SPLITS
from mpnode_cli.data.pooled import epoch_batches, taken
from mpnode_cli.signals import raise_if_interrupted
from mpnode_cli.solver import Status
from mpnode_cli.training import distributed
from mpnode_cli.training import run as runs
from mpnode_cli.training.checkpoint import Checkpoint, load_checkpoint
from mpnode_cli.training.checkpointer import Checkpointer
from mpnode_cli.training.evaluate import EvalResult, evaluate, evaluate_datasets, pooled
from mpnode_cli.training.losses import LOSSES
from mpnode_cli.training.recipe import resolve_config
from mpnode_cli.training.schedule import LRSchedule
from mpnode_cli.training.setup import Progress, Run, load_data, set_up

# What other modules use; `resolve_config` lives in the recipe module and is named here
# too, beside `resolve_compile`, as the two steps that settle a config for its data.
__all__ = ["TrainingDiverged", "TrainingInterrupted", "resolve_compile", "resolve_config",
           "train"]


class TrainingInterrupted(Exception):
    """Ctrl-C or SIGTERM: `last.pt` holds the last completed epoch, `summary.json` says the
    run was interrupted, and `--resume` continues from it.

    Attributes:
        run_dir, epoch: the run and its last completed epoch.
        cause: the `KeyboardInterrupt` (an `mpnode_cli.signals.Interrupted` for SIGTERM).
    """

    def __init__(self, run_dir: Path, epoch: int, cause: BaseException | None = None):
        super().__init__(f"interrupted after epoch {epoch}")
        self.run_dir, self.epoch, self.cause = run_dir, epoch, cause


class TrainingDiverged(RuntimeError):
    """Bad steps kept coming after the lr was halved down to `min_lr`."""


def train(config: TrainConfig, *, resume: bool = False,
          progress: Progress | None = None,
          finished_ok: bool = False) -> runs.TrainSummary | None:
    """Train (or finetune, or resume) as `config` says; write the run folder.

    Returns the summary; None on the processes other than rank 0 of a torchrun launch.
    A new run that fails before its first checkpoint leaves no run folder behind. Resuming a
    run that has done its `epochs` is an error, unless `finished_ok`: then no epoch runs and
    the summary is written again (for a caller that lost it, e.g. an interrupted experiment).

    Raises:
        ValueError: unusable data, checkpoint or run folder (a one-line reason).
        FileNotFoundError: missing dataset or checkpoint.
        TrainingInterrupted: Ctrl-C or SIGTERM (after saving `last.pt` and an interrupted
            `summary.json`).
        TrainingDiverged: bad steps persisted down to `min_lr`.
    """
    made: list[tuple[Path, bool]] = []  # the new run folder, and whether it existed
    try:
        return _train(config, resume, progress, made, finished_ok)
    except BaseException:
        for run_dir, existed in made:  # a husk could neither be resumed nor reused
            runs.remove_unstarted(run_dir, keep_folder=existed)
        raise


def _train(config: TrainConfig, resume: bool, progress: Progress | None,
           made: list[tuple[Path, bool]], finished_ok: bool = False) -> runs.TrainSummary | None:
    """`train`'s body; it appends a new run folder to `made` (and whether it existed)."""
    world = distributed.world()
    emit = progress if progress is not None and world.main else (lambda event: None)

    # 1. Run setup: the data and the config settled for them, then the model from its
    # starting point (fresh, a finetune's parent, a resumed run's last.pt) and the rest.
    data = load_data(config, resume, world, emit)
    config = resolve_compile(data.config, sum(len(t) for t in data.train_sets))
    run = set_up(config, data, resume, made, finished_ok)
    config, state = run.config, run.state
    # 2.–3. The lr policy, and the checkpointer with its first snapshot: the starting point.
    schedule = LRSchedule(config, run.optimizer, state)
    saver = Checkpointer(run)
    if not run.resumed:
        schedule.start()
    emit({"event": "start", "run_dir": str(run.run_dir), "first_epoch": state.epoch + 1,
          "epochs": config.epochs,
          "batches": sum(math.ceil(len(t) / config.batch_size) for t in run.train_sets),
          "parameters": _count(run.model), "solver": _describe_solver(config),
          "processes": world.size, "backend": world.backend, "stream": config.stream})

    # 4. Epochs, each trained, validated and saved; epoch 0 validates the starting weights.
    try:
        if state.epoch == 0 and not runs.checkpoint_path(run.run_dir, "best").exists():
            runs.truncate_metrics(run.run_dir, -1)  # again, if interrupted before
            val, each = _validate(run)
            row = _record(run, schedule, 0, val, each, None, val.seconds)
            saver.save_epoch(row, best=True)
            emit({"event": "epoch", **row})
        for epoch in range(state.epoch + 1, config.epochs + 1):
            start = time.perf_counter()
            steps = _train_epoch(run, schedule, saver, epoch)
            val, each = _validate(run)
            state.epoch = epoch
            row = _record(run, schedule, epoch, val, each, steps, time.perf_counter() - start)
            saver.save_epoch(row, best=row["improved"])
            emit({"event": "epoch", **row})
    except KeyboardInterrupt as exc:
        saver.save_interrupted(exc)
        raise TrainingInterrupted(run.run_dir, saver.snapshot.epoch, exc) from None
    if not world.main:
        return None

    # 5. The best weights on the test split, plots, summary.json.
    return _finish(run)


def _train_epoch(run: Run, schedule: LRSchedule, saver: Checkpointer,
                 epoch: int) -> dict[str, Any]:
    """One pass over the shuffled train split (of each dataset: every batch is one
    dataset's, `mpnode_cli.data.pooled.epoch_batches`); returns the epoch's step
    statistics (`horizon`: the longest dataset's)."""
    start = time.perf_counter()
    config, world, state, loss_fn = run.config, run.world, run.state, LOSSES[run.config.loss]
    horizons = [_horizon(config, epoch, t.time.numel()) for t in run.train_sets]
    times = [t.time[:h].to(run.device) for t, h in zip(run.train_sets, horizons, strict=True)]
    loss_sum, count, grad_norms, evals_per_batch, skipped = 0.0, 0, [], [], []
    batches = epoch_batches([len(t) for t in run.train_sets], config.batch_size,
                            config.even_batches, run.shuffle)
    # This rank's slice of each global batch (all of it), read ahead when streamed.
    parts = [(i, idx[world.shard(len(idx))]) for i, idx in batches]
    with taken(run.train_sets, parts) as batches_taken:
        for b, ((i, idx), batch) in enumerate(zip(batches, batches_taken, strict=True),
                                              start=1):
            x, u = _inputs(run, batch, len(idx), horizons[i])
            loss, grad_norm, evals, reason = _step(run.model, run.optimizer, x, times[i],
                                                   batch.graph(run.device), u, loss_fn,
                                                   config, world, len(batch) / len(idx))
            raise_if_interrupted()  # a signal a library swallowed inside the step
            evals_per_batch.append(evals)
            if reason is None:
                loss_sum, count = loss_sum + loss * len(idx), count + len(idx)
                grad_norms.append(grad_norm)
                state.bad_run = 0
                run.emit({"event": "batch", "epoch": epoch, "batch": b,
                          "batches": len(batches), "loss": loss})
                continue
            skipped.append(f"batch {b}: {reason}")
            state.skipped, state.bad_run = state.skipped + 1, state.bad_run + 1
            run.emit({"event": "skip", "epoch": epoch, "batch": b, "reason": reason})
            if state.bad_run >= config.max_bad_steps:
                _roll_back(run, schedule, saver.snapshot, epoch, reason)
    # A batch's RHS evaluations are its slowest trajectory's, wherever that was solved.
    n_f_evals = int(world.max(torch.tensor(evals_per_batch, dtype=torch.long)).sum())
    return {"train_loss": loss_sum / count if count else math.nan, "horizon": max(horizons),
            "grad_norm": sum(grad_norms) / len(grad_norms) if grad_norms else math.nan,
            "rhs_evals": n_f_evals, "skipped": len(skipped), "skip_reasons": skipped,
            "train_seconds": time.perf_counter() - start}


def _inputs(run: Run, batch, size: int, horizon: int
            ) -> tuple[torch.Tensor, torch.Tensor | None]:
    """This rank's part of a global batch of `size` trajectories, normalized, noised and on
    the device, over its first `horizon` samples: `x: [B_r, H, N, D]`, `u: [B_r, H, N, U]`
    (None without controls)."""
    x = run.normalizer.norm_x(batch.states[:, :horizon])  # (B_r, H, N, D)
    # Noise is drawn on the CPU from the loop's generator for the whole global batch, so it
    # is the same on any device, after a resume and with any number of processes.
    noise = torch.randn((size, *x.shape[1:]), generator=run.shuffle)[run.world.shard(size)]
    x = (x + run.config.noise * noise).to(run.device)
    u = None if batch.controls is None else run.normalizer.norm_u(
        batch.controls[:, :horizon]).to(run.device)
    return x, u


def _roll_back(run: Run, schedule: LRSchedule, snapshot: Checkpoint, epoch: int,
               reason: str) -> None:
    """After `max_bad_steps` bad batches in a row: back to the last completed epoch's
    weights and moments (`snapshot`), on at half the lr.

    Raises:
        TrainingDiverged: half the lr is below `min_lr`.
    """
    lr = schedule.retry_lr()
    if lr is None:
        raise TrainingDiverged(
            f"{run.state.bad_run} bad steps in a row at lr {schedule.lr:.3g} ({reason}); "
            "try a smaller --lr, looser --rtol/--atol or --fixed-dt")
    run.model.load_state_dict(snapshot.state_dict)
    run.optimizer.load_state_dict(copy.deepcopy(snapshot.optimizer))
    schedule.restart(lr)
    run.state.bad_run, run.state.restores = 0, run.state.restores + 1
    run.emit({"event": "restore", "epoch": epoch, "lr": lr})


def _step(model, optimizer, x, ts, adjacency, u, loss_fn, config: TrainConfig,
          world: distributed.World, share: float = 1.0):
    """One update from this rank's `x: [B_r, H, N, D]`, the fraction `share` = B_r / B of
    the global batch (all of it in one process).

    Returns (the global batch's loss, grad norm, this rank's RHS evals, skip reason).
    """
    optimizer.zero_grad(set_to_none=True)
    loss, evals, status = None, 0, torch.zeros(0, dtype=torch.long)
    if len(x):  # a rank's slice is empty when the batch has fewer trajectories than ranks
        batch = model.training_loss(x, ts, adjacency, u, loss_fn, solver=config.solver)
        loss, evals, status = batch.loss, batch.n_f_evals, batch.status
    # Summed over ranks, so that every rank takes the same decision: failed solves per
    # status, non-finite losses, and the batch's mean loss (each rank's weighted by share).
    verdict = torch.zeros(len(Status) + 2, dtype=torch.float64)
    value = None if loss is None else loss.item()
    if value is not None and not math.isfinite(value):
        verdict[-2] = 1
    elif value is not None:
        verdict[-1] = value * share
    elif len(x):
        verdict[:len(Status)] = torch.bincount(status.cpu(), minlength=len(Status))
    verdict = world.sum(verdict)
    failed = int(verdict[1:len(Status)].sum())
    if failed:
        worst = Status(int(verdict[:len(Status)].nonzero().max())).name
        return math.nan, math.nan, evals, f"solver {worst} on {failed} trajectories"
    if verdict[-2] > 0:
        return math.nan, math.nan, evals, "non-finite loss"
    if loss is not None:
        loss.backward()
    world.sum_gradients(list(model.parameters()), share)  # the global batch's gradient
    norm = float(torch.nn.utils.clip_grad_norm_(model.parameters(), config.clip))
    if not math.isfinite(norm):
        optimizer.zero_grad(set_to_none=True)
        return math.nan, norm, evals, "non-finite gradient"
    optimizer.step()
    return float(verdict[-1]), norm, evals, None


def _validate(run: Run) -> tuple[EvalResult, list[EvalResult]]:
    """The pooled validation result (the loss that selects the best epoch) and each
    dataset's; each rank rolls out its part, and the error sums are added over ranks."""
    world = run.world
    each = [evaluate(run.model, part, run.normalizer, batch_size=run.config.val_batch_size,
                     solver=run.config.solver, device=run.device,
                     combine=world.sum if world.size > 1 else None) for part in run.val_parts]
    return pooled(each, [d.num_nodes for d in run.datas]), each


def _record(run: Run, schedule: LRSchedule, epoch: int, val: EvalResult,
            each: list[EvalResult], steps: dict | None, seconds: float) -> dict[str, Any]:
    """Update the best epoch from the validation result and set the next epoch's lr; return
    the metrics row (`lr`: the one this epoch ran at)."""
    config, state = run.config, run.state
    val_loss = val.loss(config.loss)
    improved = val_loss < state.best_val
    lr = schedule.lr
    if improved:
        state.best_val, state.best_epoch = val_loss, epoch
    schedule.end_epoch(epoch, improved)
    state.seconds += seconds
    steps = steps or {"train_loss": None, "horizon": None, "grad_norm": None,
                      "rhs_evals": 0, "skipped": 0, "skip_reasons": [], "train_seconds": 0.0}
    return {"epoch": epoch, **steps, "val_loss": val_loss, "val_mse": val.mse,
            "val_failed": val.failed, "val_rhs_evals": val.n_f_evals, "lr": lr,
            "seconds": seconds, "improved": improved} | _by_dataset(run.names, each, config)


def _by_dataset(names: list[str], each: list[EvalResult], config: TrainConfig
                ) -> dict[str, Any]:
    """A metrics row's per-dataset validation values (none for one dataset, whose row keeps
    the keys it always had)."""
    if len(each) == 1:
        return {}
    pairs = list(zip(names, each, strict=True))
    return {"val_loss_by_dataset": {n: r.loss(config.loss) for n, r in pairs},
            "val_mse_by_dataset": {n: r.mse for n, r in pairs},
            "val_failed_by_dataset": {n: r.failed for n, r in pairs}}


def _finish(run: Run) -> runs.TrainSummary:
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
    summary = runs.TrainSummary(
        run_dir=str(run.run_dir), model=run.kind, model_config=run.model_config,
        parameters=_count(run.model), dataset=str(config.datasets[0]),
        dataset_fingerprint=data.fingerprint, system=data.system,
        num_nodes=data.num_nodes, loss=config.loss, epochs=state.epoch,
        best_epoch=state.best_epoch, min_val_loss=state.best_val,
        min_val_mse=best.metrics.get("val_mse"), table2=state.best_epoch * state.best_val,
        test=test and test["result"], wall_seconds=state.seconds,
        baselines=test and test["baselines"],
        seconds_per_epoch=runs.seconds_per_epoch(run.run_dir), skipped_batches=state.skipped,
        restores=state.restores,
        init_checkpoint=None if config.init_checkpoint is None else str(config.init_checkpoint),
        parent_sha256=run.parent_sha, world_size=run.world.size,
        by_dataset=_summary_by_dataset(run.names, run.facts, best, test),
    )  # fmt: skip
    runs.write_json(run.run_dir / runs.SUMMARY, asdict(summary))
    return summary


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


# Compile the solver's step when a run takes at least this many optimizer steps. Compiling
# costs 10–60 s on 2 CPU cores (less from inductor's on-disk cache) and saves about 30% of
# each training step (bench/results/train.md), so it pays from a few thousand steps on.
COMPILE_MIN_STEPS = 3000


def resolve_compile(config: TrainConfig, n_train: int) -> TrainConfig:
    """Settle `solver.compile = "auto"` for a run over `n_train` trajectories.

    Compile when the run is long (≥ `COMPILE_MIN_STEPS` optimizer steps), its steps are
    adaptive (compiling does not apply to `fixed_dt`) and a C++ compiler is there for
    inductor on CPU. Shapes that change (a smaller last batch, the horizon curriculum's
    growing horizon) cost one more compile, after which torch.compile treats that size as
    dynamic (`solve`'s automatic dynamic shapes).
    """
    if config.solver.compile != "auto":
        return config
    steps = config.epochs * -(-n_train // config.batch_size)
    decide = (steps >= COMPILE_MIN_STEPS and config.solver.fixed_dt is None
              and (config.device != "cpu" or _have_cxx()))
    return config.model_copy(update={"solver": config.solver.model_copy(
        update={"compile": decide})})


def _describe_solver(config: TrainConfig) -> str:
    """One line for the run's header: the method, tolerances, controller and compile."""
    o = config.solver
    steps = f"fixed dt {o.fixed_dt:g}" if o.fixed_dt is not None else (
        f"rtol {o.rtol:g}, atol {o.atol:g}, {o.controller.upper()} controller")
    compiled = "compiled (the first epochs compile)" if o.compile is True else "not compiled"
    return f"{o.method}, {steps}, {compiled}"


def _have_cxx() -> bool:
    return shutil.which(os.environ.get("CXX", "g++")) is not None


def _horizon(config: TrainConfig, epoch: int, t: int) -> int:
    """Samples per training trajectory this epoch: all, or the curriculum's growing prefix."""
    if not config.horizon_curriculum:
        return t
    frac = min(1.0, (epoch - 1) / config.curriculum_epochs)
    start = min(config.curriculum_start, t)
    return max(2, min(t, round(start + frac * (t - start))))


def _count(model) -> int:
    return sum(p.numel() for p in model.parameters() if p.requires_grad)
