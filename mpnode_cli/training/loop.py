"""Training and finetuning, top to bottom: `train(config) -> TrainSummary`.

The loop is the authors' (MPNODE.jl, exps/train_pipeline.jl and src/learn.jl): z-scored
data, whole-horizon single shooting from x(t₀), Adam with global-norm clipping, 1e-4
Gaussian noise on the normalized training data, the best-validation weights kept. Its
choices (loss, batches, lr schedule, curriculum, aggregation) come from a recipe
(`mpnode_cli.training.recipe`): mpnode's measured one by default, the paper's exact one on
request. Departures from the authors in every recipe: normalization is fitted on the train
split only; the validation loss is a mean over trajectories (not over batches); a separate
test split is reported at the end.

Finetuning is this same function started from another point: `config.init_checkpoint`
supplies the weights and the architecture (and, unless `renormalize`, the normalization);
the optimizer is fresh. Resuming (`resume=True`) restores a run's `last.pt` — weights,
optimizer, RNG states and the loop's counters — so 2 + 2 epochs equal 4.

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
from collections.abc import Callable
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import torch

from mpnode_cli.config import TrainConfig
from mpnode_cli.data.dataset import SPLITS, Normalizer, TrajectoryData
from mpnode_cli.data.pooled import (
    dataset_names,
    epoch_batches,
    fewer_than_asked,
    load_datasets,
    taken,
    train_and_validation,
)
from mpnode_cli.data.stream import StreamedTrajectories
from mpnode_cli.models.registry import OPTIONS, build_model, model_class, resolve_options
from mpnode_cli.paths import check_output_folder
from mpnode_cli.signals import deferred_signals, raise_if_interrupted, signal_name
from mpnode_cli.solver import Status
from mpnode_cli.training import distributed
from mpnode_cli.training import run as runs
from mpnode_cli.training.checkpoint import Checkpoint, file_sha256, load_checkpoint, save_checkpoint
from mpnode_cli.training.evaluate import (
    EvalResult,
    check_compatible,
    evaluate,
    evaluate_datasets,
    pooled,
)
from mpnode_cli.training.extrapolation import training_range
from mpnode_cli.training.losses import LOSSES
from mpnode_cli.training.optim import Adam
from mpnode_cli.training.recipe import resolve_recipe

Progress = Callable[[dict[str, Any]], None]


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


@dataclass
class LoopState:
    """The loop's counters, saved in every checkpoint so that a resume continues exactly."""

    epoch: int = 0
    best_epoch: int = 0
    best_val: float = math.inf
    since_best: int = 0
    bad_run: int = 0
    skipped: int = 0
    restores: int = 0
    seconds: float = 0.0
    lr_scale: float = 1.0


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
    if not resume and world.main:  # the run folder's place must be writable before any work
        check_output_folder(config.run_dir or runs.default_root())

    # 1. Data: each dataset's train split (optionally its first K trajectories) and validation
    # split, in memory or (`stream`, one dataset) read from the file batch by batch. The
    # first dataset's system and recipe resolve the config (`mpnode_cli.data.pooled`).
    datas = load_datasets(config.datasets, config.stream)
    data = datas[0]
    # Absolute paths, so that a run can be resumed and evaluated from any folder.
    paths = [Path(p).resolve() for p in config.datasets]
    config = config.model_copy(update={"dataset": paths[0] if len(paths) == 1 else paths} | (
        {"init_checkpoint": Path(config.init_checkpoint).resolve()}
        if config.init_checkpoint is not None else {}))
    if not resume:  # a resumed run's config.json is already resolved
        config = resolve_config(config, data)
    device = _device(config.device)
    loss_fn = LOSSES[config.loss]
    train_sets, val_sets = train_and_validation(datas, config.trajectories)
    if note := fewer_than_asked(datas, train_sets, config.trajectories):
        emit({"event": "warning", "text": note})
    config = resolve_compile(config, sum(len(t) for t in train_sets))

    # 2. The starting point: fresh weights, a parent checkpoint (finetune), or last.pt (resume).
    if resume and config.run_dir is None:
        raise ValueError("resume needs the run folder (run_dir)")
    parent = None if resume or config.init_checkpoint is None else load_checkpoint(
        config.init_checkpoint)
    last = load_checkpoint(runs.checkpoint_path(config.run_dir, "last")) if resume else None
    source = last or parent
    if last is not None:
        _check_same_data(last, datas)
    if last is not None and config.epochs <= last.epoch and not finished_ok:
        raise ValueError(f"{config.run_dir} has trained {last.epoch} epochs already; --epochs "
                         f"is the total, so give more than {last.epoch} to continue it")
    if source is not None:
        kind, model_config = source.model_kind, source.model_config
        for each in datas:
            check_compatible(kind, model_config, source.dataset["num_nodes"], each,
                             "finetune" if parent else "resume", source.dataset.get("system"),
                             allow_other_system=config.allow_other_system)
    else:  # sizes from the data, options as resolved
        kind, model_config = config.model, {
            "node_dim": data.node_dim, "control_dim": data.control_dim,
            "num_nodes": data.num_nodes, **config.model_options}
        _check_one_size(kind, datas)
    torch.manual_seed(config.seed)
    try:
        model = build_model(kind, model_config)
    except (MemoryError, RuntimeError) as exc:  # torch reports a failed allocation so
        raise ValueError(f"cannot build model '{kind}' with {model_config}: out of memory "
                         f"({str(exc).splitlines()[0][:80]})") from None
    # config.json tells the truth: the architecture is what was built.
    model_config = model.config
    config = config.model_copy(update={"model": kind,
                                       "model_options": model.options.model_dump()})
    # The default name holds the time and whatever suffix makes it new: rank 0 chooses it.
    run_dir = world.from_main(
        lambda: Path(config.run_dir or runs.default_run_dir(config.datasets, kind)))
    config = config.model_copy(update={"run_dir": run_dir})
    if source is not None and not (parent and config.renormalize):
        normalizer = source.build_normalizer()
    elif config.stream:
        normalizer = train_sets[0].fit_normalizer()  # one pass over the file, in blocks
    else:  # several datasets: on their train splits pooled
        normalizer = _fit_normalizer(train_sets)
    parent_sha = last.parent_sha256 if last else (
        file_sha256(config.init_checkpoint) if parent else None)

    if source is not None:
        model.load_state_dict(source.state_dict)
    if source is None or (parent and config.renormalize):
        # Statistics of this train split: L2S's one-step differences, PNA's degree δ.
        _fit_statistics(model, train_sets, normalizer)
    model.to(device)
    world.broadcast_module(model)
    optimizer = Adam(model.parameters(), lr=config.lr)
    shuffle = torch.Generator().manual_seed(config.seed)  # batch order and noise
    state = LoopState()
    if last is not None:
        optimizer.load_state_dict(last.optimizer)
        torch.set_rng_state(last.rng["torch"])
        shuffle.set_state(last.rng["shuffle"])
        state = LoopState(**last.loop)
    if not world.main:
        # The only draws from torch's global generator in training are L2S's step noise on
        # each rank's own slice: other ranks must not repeat rank 0's draws.
        torch.manual_seed(hash((config.seed, world.rank, state.epoch)))

    def open_run() -> None:  # rank 0's
        if last is not None:
            runs.truncate_metrics(run_dir, state.epoch)
        else:
            made.append((run_dir, not runs.create(run_dir)))
        runs.write_json(run_dir / runs.CONFIG, config.model_dump(mode="json"))

    world.from_main(open_run)

    facts = _dataset_facts(data, config.datasets[0])
    if len(datas) > 1:  # every dataset's; the first's stay at the top, where readers look
        facts["datasets"] = [_dataset_facts(d, p)
                             for d, p in zip(datas, config.datasets, strict=True)]
    facts["train_range"] = training_range(*train_sets).to_dict()  # over every dataset

    def checkpoint(metrics: dict[str, Any] | None = None) -> Checkpoint:
        return Checkpoint(
            model_kind=kind, model_config=model_config, state_dict=model.state_dict(),
            normalizer=normalizer.to_dict(), train_config=config.model_dump(mode="json"),
            dataset=facts, epoch=state.epoch, optimizer=optimizer.state_dict(),
            rng={"torch": torch.get_rng_state(), "shuffle": shuffle.get_state()},
            loop=asdict(state), parent_sha256=parent_sha, metrics=metrics or {},
        )  # fmt: skip

    # Each rank validates its part of each split; the error sums are added over ranks.
    val_parts = [v.select(torch.arange(len(v))[world.shard(len(v))]) for v in val_sets]
    names = dataset_names(config.datasets)

    def validate() -> tuple[EvalResult, list[EvalResult]]:
        """The pooled result (the loss that selects the best epoch) and each dataset's."""
        each = [evaluate(model, part, normalizer, batch_size=config.val_batch_size,
                         solver=config.solver, device=device,
                         combine=world.sum if world.size > 1 else None) for part in val_parts]
        return pooled(each, [d.num_nodes for d in datas]), each

    # 3. Epochs. The snapshot is the last completed epoch: what last.pt holds, what a run of
    # bad steps rolls back to, and what Ctrl-C leaves behind.
    snapshot = _snapshot(checkpoint())
    batches = sum(math.ceil(len(t) / config.batch_size) for t in train_sets)
    if config.schedule == "cosine" and last is None:
        _set_lr(optimizer, _cosine_lr(config, 1))
    emit({"event": "start", "run_dir": str(run_dir), "first_epoch": state.epoch + 1,
          "epochs": config.epochs, "batches": batches, "parameters": _count(model),
          "solver": _describe_solver(config), "processes": world.size,
          "backend": world.backend, "stream": config.stream})
    try:
        if state.epoch == 0 and not runs.checkpoint_path(run_dir, "best").exists():
            # Epoch 0: how good the starting weights are (again, if interrupted before).
            runs.truncate_metrics(run_dir, -1)
            val, each = validate()
            row = _record(state, 0, val, config, None, optimizer, val.seconds) | _by_dataset(
                names, each, config)
            with deferred_signals():  # the epoch's files all or none (see _save_epoch)
                snapshot = _snapshot(checkpoint())
                _save_epoch(world, run_dir, row, snapshot, checkpoint, best=True)
            emit({"event": "epoch", **row})
        for epoch in range(state.epoch + 1, config.epochs + 1):
            start = time.perf_counter()
            steps = _train_epoch(model, optimizer, train_sets, normalizer, loss_fn, config,
                                 state, snapshot, shuffle, epoch, device, emit, world)
            val, each = validate()
            state.epoch = epoch
            row = _record(state, epoch, val, config, steps, optimizer,
                          time.perf_counter() - start) | _by_dataset(names, each, config)
            with deferred_signals():
                snapshot = _snapshot(checkpoint())
                _save_epoch(world, run_dir, row, snapshot, checkpoint, best=row["improved"])
            emit({"event": "epoch", **row})
    except KeyboardInterrupt as exc:
        if world.main:
            try:
                with deferred_signals():  # a second signal must not cut the save short
                    save_checkpoint(runs.checkpoint_path(run_dir, "last"), snapshot)
                    runs.write_interrupted(run_dir, snapshot.epoch, signal_name(exc))
            except KeyboardInterrupt:
                pass  # it came during the save, which finished: stop, as both signals asked
        raise TrainingInterrupted(run_dir, snapshot.epoch, exc) from None
    if not world.main:
        return None

    # 4. The best weights on the test split (of each dataset that has one; pooled), plots,
    # summary.json.
    best = load_checkpoint(runs.checkpoint_path(run_dir, "best"))
    emit({"event": "test"})
    test = None
    if any(bool((d.split == SPLITS["test"]).any()) for d in datas):
        test = evaluate_datasets(best, datas, names, split="test", verb="test",
                                 batch_size=config.val_batch_size, device=device,
                                 plot_dir=run_dir / "plots" if config.plots else None)
    summary = runs.TrainSummary(
        run_dir=str(run_dir), model=kind, model_config=model_config, parameters=_count(model),
        dataset=str(config.datasets[0]), dataset_fingerprint=data.fingerprint,
        system=data.system,
        num_nodes=data.num_nodes, loss=config.loss, epochs=state.epoch,
        best_epoch=state.best_epoch, min_val_loss=state.best_val,
        min_val_mse=best.metrics.get("val_mse"), table2=state.best_epoch * state.best_val,
        test=test and test["result"], wall_seconds=state.seconds,
        baselines=test and test["baselines"],
        seconds_per_epoch=runs.seconds_per_epoch(run_dir), skipped_batches=state.skipped,
        restores=state.restores,
        init_checkpoint=None if config.init_checkpoint is None else str(config.init_checkpoint),
        parent_sha256=parent_sha, world_size=world.size,
        by_dataset=_summary_by_dataset(names, facts, best, test),
    )  # fmt: skip
    runs.write_json(run_dir / runs.SUMMARY, asdict(summary))
    return summary


def _save_epoch(world, run_dir: Path, row: dict[str, Any], snapshot: Checkpoint, checkpoint,
                *, best: bool) -> None:
    """An epoch's files: its metrics row, `last.pt` (`snapshot`), and `best.pt` if it
    improved (rank 0 only).

    The caller holds signals (`deferred_signals`) around this and the assignment of
    `snapshot`, so an interrupt comes after all three writes or before any; the interrupt
    handler then saves the snapshot it has, and `last.pt`'s epoch is always the last row
    of metrics.jsonl.
    """
    if not world.main:
        return
    if best:
        save_checkpoint(runs.checkpoint_path(run_dir, "best"), checkpoint(row))
    runs.append_metrics(run_dir, row)
    save_checkpoint(runs.checkpoint_path(run_dir, "last"), snapshot)


def _train_epoch(model, optimizer, train_sets: list[TrajectoryData | StreamedTrajectories],
                 normalizer: Normalizer,
                 loss_fn, config: TrainConfig, state: LoopState, snapshot: Checkpoint,
                 shuffle: torch.Generator, epoch: int, device, emit: Progress,
                 world: distributed.World) -> dict:
    """One pass over the shuffled train split (of each dataset: every batch is one
    dataset's, `mpnode_cli.data.pooled.epoch_batches`); returns the epoch's step
    statistics (`horizon`: the longest dataset's)."""
    start = time.perf_counter()
    horizons = [_horizon(config, epoch, t.time.numel()) for t in train_sets]
    times = [t.time[:h].to(device) for t, h in zip(train_sets, horizons, strict=True)]
    loss_sum, count, grad_norms, evals_per_batch, skipped = 0.0, 0, [], [], []
    batches = epoch_batches([len(t) for t in train_sets], config.batch_size,
                            config.even_batches, shuffle)
    # This rank's slice of each global batch (all of it), read ahead when streamed.
    parts = [(i, idx[world.shard(len(idx))]) for i, idx in batches]
    with taken(train_sets, parts) as batches_taken:
        for b, ((i, idx), batch) in enumerate(zip(batches, batches_taken, strict=True),
                                              start=1):
            horizon, ts = horizons[i], times[i]
            part = world.shard(len(idx))
            x = normalizer.norm_x(batch.states[:, :horizon])  # (B_r, H, N, D)
            # Noise is drawn on the CPU from the loop's generator for the whole global batch,
            # so it is the same on any device, after a resume and with any number of processes.
            noise = torch.randn((len(idx), *x.shape[1:]), generator=shuffle)[part]
            x = (x + config.noise * noise).to(device)
            u = None if batch.controls is None else normalizer.norm_u(
                batch.controls[:, :horizon]).to(device)
            loss, grad_norm, evals, reason = _step(model, optimizer, x, ts,
                                                   batch.graph(device), u, loss_fn,
                                                   config, world, len(batch) / len(idx))
            raise_if_interrupted()  # a signal a library swallowed inside the step
            evals_per_batch.append(evals)
            if reason is None:
                loss_sum, count = loss_sum + loss * len(idx), count + len(idx)
                grad_norms.append(grad_norm)
                state.bad_run = 0
                emit({"event": "batch", "epoch": epoch, "batch": b, "batches": len(batches),
                      "loss": loss})
                continue
            skipped.append(f"batch {b}: {reason}")
            state.skipped, state.bad_run = state.skipped + 1, state.bad_run + 1
            emit({"event": "skip", "epoch": epoch, "batch": b, "reason": reason})
            if state.bad_run >= config.max_bad_steps:
                lr = optimizer.param_groups[0]["lr"] / 2
                if lr < config.min_lr:
                    raise TrainingDiverged(
                        f"{state.bad_run} bad steps in a row at lr {2 * lr:.3g} ({reason}); "
                        "try a smaller --lr, looser --rtol/--atol or --fixed-dt")
                # Roll back to the last completed epoch's weights and moments at half the lr.
                model.load_state_dict(snapshot.state_dict)
                optimizer.load_state_dict(copy.deepcopy(snapshot.optimizer))
                _set_lr(optimizer, lr)
                state.bad_run, state.restores = 0, state.restores + 1
                state.lr_scale /= 2
                emit({"event": "restore", "epoch": epoch, "lr": lr})
    # A batch's RHS evaluations are its slowest trajectory's, wherever that was solved.
    n_f_evals = int(world.max(torch.tensor(evals_per_batch, dtype=torch.long)).sum())
    return {"train_loss": loss_sum / count if count else math.nan, "horizon": max(horizons),
            "grad_norm": sum(grad_norms) / len(grad_norms) if grad_norms else math.nan,
            "rhs_evals": n_f_evals, "skipped": len(skipped), "skip_reasons": skipped,
            "train_seconds": time.perf_counter() - start}


def _check_same_data(last: Checkpoint, datas: list) -> None:
    """Refuse to resume a run on other data than it trained on (by fingerprint, in order)."""
    records = last.dataset.get("datasets") or [last.dataset]
    if [r["fingerprint"] for r in records] == [d.fingerprint for d in datas]:
        return
    if len(records) == 1 and len(datas) == 1:
        raise ValueError(f"{datas[0].path} is not the dataset this run trained on (its "
                         "fingerprint differs from the run's): resume needs the same data")
    given = ", ".join(str(d.path) for d in datas)
    raise ValueError(f"{given} are not the {len(records)} datasets this run trained on, in "
                     "its order (their fingerprints differ from the run's): resume needs the "
                     "same data")


def _check_one_size(kind: str, datas: list) -> None:
    """Refuse datasets of several N for a model built for one node count."""
    sizes = sorted({d.num_nodes for d in datas})
    if len(sizes) > 1 and kind in OPTIONS and not model_class(kind).transferable:
        raise ValueError(f"model '{kind}' runs only on graphs of the size it was built for, "
                         f"but the datasets have N = {', '.join(map(str, sizes))}: train it "
                         "on datasets of one N, or choose a model of node dynamics (mpnode)")


def _fit_normalizer(train_sets: list[TrajectoryData]) -> Normalizer:
    """The z-score of the train split, or of several datasets' train splits pooled."""
    if len(train_sets) == 1:
        return Normalizer.fit(train_sets[0].states, train_sets[0].controls)
    controls = [t.controls for t in train_sets]
    return Normalizer.fit([t.states for t in train_sets],
                          None if controls[0] is None else controls)


def _fit_statistics(model, train_sets: list, normalizer: Normalizer) -> None:
    """`model.fit_statistics` on the train split, or on several datasets' (as lists: their
    N differ; all in memory, as streaming takes one dataset)."""
    dt = float(train_sets[0].time[1] - train_sets[0].time[0])  # one dt for all datasets
    if len(train_sets) == 1:
        model.fit_statistics(_statistics_states(model, train_sets[0], normalizer), dt,
                             train_sets[0].graph())
        return
    model.fit_statistics([normalizer.norm_x(t.states) for t in train_sets], dt,
                         [t.graph() for t in train_sets])


def _dataset_facts(data, path: Path) -> dict[str, Any]:
    """What a checkpoint records of a training dataset."""
    return {"fingerprint": data.fingerprint, "path": str(path), "system": data.system,
            "num_nodes": data.num_nodes, "node_dim": data.node_dim,
            "control_dim": data.control_dim, "state_names": list(data.state_names),
            "control_names": list(data.control_names), "topology": data.attrs.get("topology")}


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


def _statistics_states(model, train_set: TrajectoryData | StreamedTrajectories,
                       normalizer: Normalizer) -> torch.Tensor | None:
    """The normalized train states `fit_statistics` gets: in memory, all of them; streamed,
    read for a model that fits on states (L2S) and None for the others (they need only
    the graphs), so that a streamed MP-NODE run never holds the train split."""
    if isinstance(train_set, TrajectoryData):
        return normalizer.norm_x(train_set.states)
    if not model.statistics_need_states:
        return None
    return normalizer.norm_x(train_set.take(torch.arange(len(train_set))).states)


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


def _record(state: LoopState, epoch: int, val: EvalResult, config: TrainConfig,
            steps: dict | None, optimizer, seconds: float) -> dict[str, Any]:
    """Update best/plateau counters from the validation result; return the metrics row."""
    val_loss = val.loss(config.loss)
    improved = val_loss < state.best_val
    lr = optimizer.param_groups[0]["lr"]
    if improved:
        state.best_val, state.best_epoch, state.since_best = val_loss, epoch, 0
    elif epoch > 0:
        state.since_best += 1
        if (config.schedule == "plateau" and state.since_best >= config.patience
                and lr / 2 >= config.min_lr):
            _set_lr(optimizer, lr / 2)  # the next epoch runs at the halved rate
            state.since_best = 0
    if config.schedule == "cosine" and epoch > 0:
        # The next epoch's rate; rollbacks after bad steps halve the whole curve.
        _set_lr(optimizer, _cosine_lr(config, epoch + 1) * state.lr_scale)
    state.seconds += seconds
    steps = steps or {"train_loss": None, "horizon": None, "grad_norm": None,
                      "rhs_evals": 0, "skipped": 0, "skip_reasons": [], "train_seconds": 0.0}
    return {"epoch": epoch, **steps, "val_loss": val_loss, "val_mse": val.mse,
            "val_failed": val.failed, "val_rhs_evals": val.n_f_evals, "lr": lr,
            "seconds": seconds, "improved": improved}


def resolve_config(config: TrainConfig, data: TrajectoryData) -> TrainConfig:
    """Fill what `config` was not given from its recipe (for `data`), then check the model
    and its options and fill in the options' defaults.

    A finetune's model comes from its checkpoint, so its model options are left as they are.

    Raises:
        ValueError: unknown model, or an option the model does not declare or refuses
            (one line naming the model and the option).
    """
    finetune = config.init_checkpoint is not None
    declared = () if finetune or config.model not in OPTIONS else OPTIONS[config.model].model_fields
    config = resolve_recipe(config, data.system, data.attrs.get("recipe"), data.time.numel(),
                            lambda name: name in declared)
    if finetune:
        return config
    options = resolve_options(config.model, config.model_options)
    return config.model_copy(update={"model_options": options.model_dump()})


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


def _snapshot(ckpt: Checkpoint) -> Checkpoint:
    """A deep copy: the optimizer and model update their tensors in place."""
    return copy.deepcopy(ckpt)


def _cosine_lr(config: TrainConfig, epoch: int) -> float:
    """Cosine decay from `lr` (epoch 1) to `min_lr` (after the last epoch)."""
    frac = min(1.0, (epoch - 1) / max(config.epochs, 1))
    return config.min_lr + 0.5 * (config.lr - config.min_lr) * (1 + math.cos(math.pi * frac))


def _set_lr(optimizer, lr: float) -> None:
    for group in optimizer.param_groups:
        group["lr"] = lr


def _count(model) -> int:
    return sum(p.numel() for p in model.parameters() if p.requires_grad)


def _device(name: str) -> torch.device:
    if name == "cuda" and not torch.cuda.is_available():
        raise ValueError("--device cuda asked for, but torch sees no CUDA device")
    return torch.device(name)
