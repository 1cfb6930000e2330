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
2. the learning rate, one policy (`mpnode_cli.training.lr_schedule.LRSchedule`);
3. the checkpointer (`mpnode_cli.training.checkpointer.Checkpointer`): each epoch's files,
   all or none, and the snapshot a rollback and an interrupt go back to;
4. the epochs: `train_epoch` (one pass of optimizer steps,
   `mpnode_cli.training.step.train_step`), validation and the metrics row
   (`mpnode_cli.training.epoch_record`);
5. the best checkpoint on the test split, and `summary.json`
   (`mpnode_cli.training.finish`).

Finetuning is this same function started from another point: `config.init_checkpoint`
supplies the weights and the architecture (and, unless `renormalize`, the normalization);
the optimizer is fresh. Resuming (`resume=True`) restores a run's `last.pt` — weights,
optimizer, RNG states and the loop's counters — so 2 + 2 epochs equal 4
(`mpnode_cli.training.resume` says what may change).

Several datasets (`config.dataset` a list: one system, any N) are trained on at once
(`mpnode_cli.data.pooled`): each batch is one dataset's, the batches of all of them are
interleaved in a seeded order, the normalization and the model's statistics are fitted on
the train splits pooled, and validation and test are each dataset's and pooled (an
element-weighted mean, `mpnode_cli.training.eval_result.pooled`), the pooled validation loss
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

import functools
import math
import time
from contextlib import ExitStack
from pathlib import Path
from typing import Any

import torch

from mpnode_cli.config.train import TrainConfig
from mpnode_cli.data.pooled import epoch_batches, taken
from mpnode_cli.report.members import about_member, shown
from mpnode_cli.signals import raise_if_interrupted
from mpnode_cli.training import coverage, distributed
from mpnode_cli.training import run as runs
from mpnode_cli.training.checkpoint import Checkpoint
from mpnode_cli.training.checkpointer import Checkpointer
from mpnode_cli.training.epoch_record import record, validate
from mpnode_cli.training.finish import count_parameters, finish
from mpnode_cli.training.losses import LOSSES, run_angles
from mpnode_cli.training.lr_schedule import LRSchedule
from mpnode_cli.training.memory_guard import EpochPeaks, stop_if_outgrowing
from mpnode_cli.training.recipe import describe_solver, resolve_compile, resolve_train_config
from mpnode_cli.training.run_folder import RunFolder
from mpnode_cli.training.run_state import OnEvent, Run
from mpnode_cli.training.setup import load_data, set_up
from mpnode_cli.training.step import train_step
from mpnode_cli.training.stiffness import Stiffness

# What other modules use; `resolve_train_config` lives in the recipe module and is named
# here too (the recipe also holds `resolve_compile`: the two steps that settle a config).
__all__ = ["TrainingDiverged", "TrainingInterrupted", "resolve_train_config", "train"]


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
          progress: OnEvent | None = None,
          finished_ok: bool = False) -> runs.TrainSummary | None:
    """Train (or finetune, or resume) as `config` says; write the run folder.

    Returns the summary; None on the processes other than rank 0 of a torchrun launch.
    The run folder is locked while the run lasts; a resumed one is checked whole before
    anything is written (`mpnode_cli.training.run_folder`). A new run that fails before
    its first checkpoint leaves no run folder behind. Resuming a run that has done its
    `epochs` is an error, unless `finished_ok` or its summary is yet to be written: then no
    epoch runs and the summary is written (again, for a caller that lost it).

    Raises:
        ValueError: unusable data, checkpoint or run folder (a one-line reason).
        FileNotFoundError: missing dataset or checkpoint.
        TrainingInterrupted: Ctrl-C or SIGTERM (after saving `last.pt` and an interrupted
            `summary.json`).
        TrainingDiverged: bad steps persisted down to `min_lr`.
    """
    with RunFolder() as folder:  # locked while the run lasts; a failed new one removed
        return _train(config, resume, progress, folder, finished_ok)


def _train(config: TrainConfig, resume: bool, progress: OnEvent | None, folder: RunFolder,
           finished_ok: bool = False) -> runs.TrainSummary | None:
    """`train`'s body; `folder` holds the run folder (rank 0's) while it lasts."""
    world = distributed.world()
    emit = progress if progress is not None and world.main else (lambda event: None)
    if resume:  # locked, and checked whole, before anything is read into the run
        world.from_main(lambda: folder.resume(config))

    # 1. Run setup: the data and the config settled for them, then the model from its
    # starting point (fresh, a finetune's parent, a resumed run's last.pt) and the rest.
    if not resume and (config.for_graphs or config.for_in_degree):
        # `--for-graphs`: the coverage data, simulated into the reserved run folder first.
        config = world.from_main(lambda: coverage.prepare(config, folder, emit))
    data = load_data(config, resume, world, emit, reserved=config.coverage is not None)
    config = resolve_compile(data.config, sum(len(t) for t in data.train_sets))
    run = set_up(config, data, resume, folder, finished_ok)
    config, state = run.config, run.state
    # 2.–3. Each member's lr policy (a single model is an ensemble of one), and the
    # checkpointer with its first snapshot: the starting point.
    schedules = [LRSchedule(config, run.optimizer, m, group=k)
                 for k, m in enumerate(state.members)]
    saver = Checkpointer(run)
    if not run.resumed:
        for schedule in schedules:
            schedule.start()
    emit({"event": "start", "run_dir": str(run.run_dir), "first_epoch": state.epoch + 1,
          "epochs": config.epochs,
          "batches": sum(math.ceil(len(t) / config.batch_size) for t in run.train_sets),
          "parameters": count_parameters(run.model), "solver": describe_solver(config),
          "processes": world.size, "backend": world.backend, "stream": config.stream,
          "members": len(run.shuffles),
          "in_degree": run.facts.get("train_range", {}).get("in_degree")})

    # 4. Epochs, each trained, validated and saved; epoch 0 validates the starting weights.
    try:
        if state.epoch == 0 and not runs.checkpoint_path(run.run_dir, "best").exists():
            runs.truncate_metrics(run.run_dir, -1)  # again, if interrupted before
            val, each = validate(run)
            row = record(run, schedules, 0, val, each, None, val.seconds)
            saver.save_epoch(row)
            emit({"event": "epoch", **row})
        peaks, emit = EpochPeaks(run.device.type, config.memory_budget), Stiffness(emit).emit
        for epoch in range(state.epoch + 1, config.epochs + 1):
            if not run.active() or (config.time_limit and state.epoch >= 1
                                    and state.seconds >= config.time_limit):
                break  # every member stopped early (`stop_patience`), or time is up
            start = time.perf_counter()
            peaks.begin()
            steps = train_epoch(run, schedules, saver, epoch)
            val, each = validate(run)
            state.epoch = epoch
            row = record(run, schedules, epoch, val, each, steps, time.perf_counter() - start)
            saver.save_epoch(row)
            emit({"event": "epoch", **row})
            stop_if_outgrowing(run, saver.snapshot.epoch, peaks)
    except KeyboardInterrupt as exc:
        saver.save_interrupted(exc)
        raise TrainingInterrupted(run.run_dir, saver.snapshot.epoch, exc) from None
    if not world.main:
        return None

    # 5. The best weights on the test split, plots, summary.json.
    return finish(run)


def train_epoch(run: Run, schedules: list[LRSchedule], saver: Checkpointer,
                epoch: int) -> dict[str, Any]:
    """One pass over the shuffled train split (of each dataset: every batch is one
    dataset's, `mpnode_cli.data.pooled.epoch_batches`); an ensemble's members each take
    their own order, batch b of every member in one step. Returns the epoch's step
    statistics, the members' mean (`horizon`: the longest dataset's), and each member's
    under `by_member`."""
    start = time.perf_counter()
    config, world = run.config, run.world
    angles = run_angles(config.wrap_angles, run.facts, run.normalizer.x_std)
    # Bound only when angles wrap: a loss is otherwise called loss(pred, target).
    loss_fn = (LOSSES[config.loss] if angles is None
               else functools.partial(LOSSES[config.loss], angles=angles))
    horizons = [epoch_horizon(config, epoch, t.time.numel()) for t in run.train_sets]
    times = [t.time[:h].to(run.device) for t, h in zip(run.train_sets, horizons, strict=True)]
    active = run.active()
    plans = [epoch_batches([len(t) for t in run.train_sets], config.batch_size,
                           config.even_batches, run.shuffles[k]) for k in active]
    tallies = {k: _Tally() for k in active}
    evals_per_batch = []
    with ExitStack() as stack:
        # This rank's slice of each global batch (all of it), read ahead when streamed.
        streams = [stack.enter_context(taken(run.train_sets, [
            (i, idx[world.shard(len(idx))]) for i, idx in plan])) for plan in plans]
        for b, batches in enumerate(zip(*streams, strict=True), start=1):
            i, size = plans[0][b - 1][0], len(plans[0][b - 1][1])
            inputs = [_inputs(run, batch, size, horizons[i], run.shuffles[k])
                      for k, batch in zip(active, batches, strict=True)]
            graphs, share = [x.graph(run.device) for x in batches], len(batches[0]) / size
            results = train_step(run.model, run.optimizer, inputs, times[i], graphs,
                                 _scaled(loss_fn, run.loss_scale, i), config, world, active,
                                 share)
            raise_if_interrupted()  # a signal a library swallowed inside the step
            evals_per_batch.append(max(r.n_f_evals for r in results))
            for k, r in zip(active, results, strict=True):
                tallies[k].add(r.loss, r.grad_norm, size, r.skip, f"batch {b}")
                _after_step(run, schedules, saver, epoch, b, k, r.skip)
            losses = [r.loss for r in results if r.skip is None]
            if losses:
                run.emit({"event": "batch", "epoch": epoch, "batch": b,
                          "batches": len(plans[0]), "loss": sum(losses) / len(losses)})
    # A batch's RHS evaluations are its slowest trajectory's, wherever that was solved.
    n_f_evals = int(world.max(torch.tensor(evals_per_batch, dtype=torch.long)).sum())
    intervals = sum(horizons[i] - 1 for i, _ in plans[0])  # each batch's sample intervals
    rows = {k: t.row() for k, t in tallies.items()}
    return {"train_loss": _mean([r["train_loss"] for r in rows.values()]),
            "grad_norm": _mean([r["grad_norm"] for r in rows.values()]),
            "skipped": sum(r["skipped"] for r in rows.values()),
            "skip_reasons": [_of_member(run, k, reason, ", ") for k, r in rows.items()
                             for reason in r["skip_reasons"]],
            "horizon": max(horizons), "rhs_evals": n_f_evals,
            "rhs_evals_per_sample": n_f_evals / max(intervals, 1),
            "train_seconds": time.perf_counter() - start, "by_member": rows}


class _Tally:
    """One model's (or member's) losses, gradient norms and skips over an epoch."""

    def __init__(self):
        self.loss_sum, self.count, self.grad_norms, self.skipped = 0.0, 0, [], []

    def add(self, loss: float, grad_norm: float, size: int, reason: str | None,
            where: str) -> None:
        if reason is None:
            self.loss_sum, self.count = self.loss_sum + loss * size, self.count + size
            self.grad_norms.append(grad_norm)
        else:
            self.skipped.append(f"{where}: {reason}")

    def row(self) -> dict[str, Any]:
        g = self.grad_norms
        return {"train_loss": self.loss_sum / self.count if self.count else math.nan,
                "grad_norm": sum(g) / len(g) if g else math.nan,
                "skipped": len(self.skipped), "skip_reasons": self.skipped}


def _after_step(run: Run, schedules: list[LRSchedule], saver: Checkpointer, epoch: int,
                b: int, k: int, reason: str | None) -> None:
    """Member k's counters after batch b: a good step ends a run of bad ones; a bad one is
    reported, and enough in a row roll the member back."""
    member, state = run.state.members[k], run.state
    if reason is None:
        member.bad_run = 0
        return
    state.skipped, member.bad_run = state.skipped + 1, member.bad_run + 1
    run.emit({"event": "skip", "epoch": epoch, "batch": b,
              "reason": _of_member(run, k, reason)})
    if member.bad_run >= run.config.max_bad_steps:
        _roll_back(run, schedules[k], saver.snapshot, epoch, reason, k)


def _of_member(run: Run, k: int, text: str, sep: str = ": ") -> str:
    """`text` about member k, as the run's messages say it (`about_member`)."""
    return about_member(k, len(run.state.members), text, sep)


def _mean(values: list[float]) -> float:
    finite = [v for v in values if v is not None and math.isfinite(v)]
    return sum(finite) / len(finite) if finite else math.nan


def _inputs(run: Run, batch, size: int, horizon: int, generator: torch.Generator
            ) -> tuple[torch.Tensor, torch.Tensor | None]:
    """This rank's part of a global batch of `size` trajectories, normalized, noised and on
    the device, over its first `horizon` samples: `x: [B_r, H, N, D]`, `u: [B_r, H, N, U]`
    (None without controls)."""
    x = run.normalizer.norm_x(batch.states[:, :horizon])  # (B_r, H, N, D)
    # Noise is drawn on the CPU from the loop's generator (the member's) for the whole
    # global batch, so it is the same on any device, after a resume and with any number
    # of processes.
    noise = torch.randn((size, *x.shape[1:]), generator=generator)[run.world.shard(size)]
    dtype = getattr(torch, run.config.dtype)
    x = (x + run.config.noise * noise).to(run.device, dtype)
    u = None if batch.controls is None else run.normalizer.norm_u(
        batch.controls[:, :horizon]).to(run.device, dtype)
    return x, u


def _roll_back(run: Run, schedule: LRSchedule, snapshot: Checkpoint, epoch: int,
               reason: str, k: int) -> None:
    """After `max_bad_steps` bad batches in a row: member k (the model, for one) back to the
    last completed epoch's weights and moments (`snapshot`), on at half the lr. Where half
    the lr is below `min_lr`, the member stops at its best weights and the others go on.

    Raises:
        TrainingDiverged: the member that stops was the last one training.
    """
    lr, members = schedule.retry_lr(), len(run.state.members)
    if lr is None:
        run.state.members[k].stopped = epoch
        if not run.active():
            raise TrainingDiverged(_of_member(
                run, k, f"{schedule.state.bad_run} bad steps in a row at lr "
                f"{schedule.lr:.3g} ({reason}); try a smaller --lr, looser --rtol/--atol or "
                "--fixed-dt"))
        run.emit({"event": "warning", "text": f"member {k} kept failing down to lr "
                  f"{schedule.lr:.3g} ({reason}); it stops at its best epoch"})
        return
    run.members[k].load_state_dict(run.model.member_state(snapshot.state_dict, k))
    run.optimizer.load_group_state(snapshot.optimizer, k)
    schedule.restart(lr)
    schedule.state.bad_run, run.state.restores = 0, run.state.restores + 1
    run.emit({"event": "restore", "epoch": epoch, "lr": lr} | (shown(members, {"member": k})
                                                               or {}))


def _scaled(loss_fn, scale: list[float] | None, i: int):
    """`loss_fn` times dataset i's factor (`--balance-datasets`); itself without one."""
    if scale is None:
        return loss_fn
    return lambda pred, target: loss_fn(pred, target) * scale[i]


def epoch_horizon(config: TrainConfig, epoch: int, t: int) -> int:
    """Samples per training trajectory this epoch: all, or the curriculum's growing prefix."""
    if not config.horizon_curriculum:
        return t
    frac = min(1.0, (epoch - 1) / config.curriculum_epochs)
    start = min(config.curriculum_start, t)
    return max(2, min(t, round(start + frac * (t - start))))

