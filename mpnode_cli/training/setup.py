"""A training run's setup: what the epochs work with, a `Run`
(`mpnode_cli.training.run_state`).

Two calls, `load_data` and `set_up`, with the recipe's `resolve_compile` between them (it
settles compiling by the number of train trajectories). In this order, which is the order
of the draws from torch's generator, so that one seed makes one run:
1. the data: each dataset's train split (optionally its first K trajectories) and
   validation split, in memory or (`stream`, one dataset) read from the file batch by
   batch; the first dataset's system and recipe resolve the config
   (`mpnode_cli.training.recipe`, `mpnode_cli.data.pooled`);
2. the starting point: fresh weights, a parent checkpoint (finetune) or the run's
   `last.pt` (resume: `mpnode_cli.training.resume` says what must match);
3. the model, built after seeding, and the normalizer: the starting point's, or fitted on
   the train splits (pooled);
4. Adam, the loop's generator (batch order and noise) and its counters, restored from
   `last.pt` on resume;
5. the run folder: made and locked (a new run) or brought back to `last.pt`'s epoch
   (resume: locked and checked before the setup began, `mpnode_cli.training.run_folder`),
   with the resolved `config.json`.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch

from mpnode_cli.config.train import TrainConfig
from mpnode_cli.data.dataset import Normalizer, TrajectoryData
from mpnode_cli.data.pooled import (
    check_ground_truth,
    dataset_names,
    fewer_than_asked,
    load_datasets,
    train_and_validation,
)
from mpnode_cli.data.size import check_steps, solver_steps
from mpnode_cli.data.stream import StreamedTrajectories
from mpnode_cli.devices import torch_device
from mpnode_cli.models.registry import OPTIONS, build_model, model_class
from mpnode_cli.paths import check_output_folder
from mpnode_cli.training import distributed, step_memory
from mpnode_cli.training import run as runs
from mpnode_cli.training.checkpoint import Checkpoint, file_sha256, load_checkpoint
from mpnode_cli.training.compat import check_compatible
from mpnode_cli.training.losses import dataset_loss_scale
from mpnode_cli.training.optim import Adam
from mpnode_cli.training.recipe import resolve_train_config
from mpnode_cli.training.resume import check_resumable
from mpnode_cli.training.run_folder import RunFolder
from mpnode_cli.training.run_state import LoopState, MemberState, OnEvent, Run
from mpnode_cli.training.train_range import training_range


@dataclass
class RunData:
    """The setup's first stage (`load_data`): the data, and the config resolved for them
    but for `solver.compile`, which `mpnode_cli.training.recipe.resolve_compile` settles by
    the number of train trajectories."""

    config: TrainConfig
    world: distributed.World
    emit: OnEvent
    datas: list[TrajectoryData | StreamedTrajectories]
    train_sets: list[TrajectoryData | StreamedTrajectories]
    val_sets: list[TrajectoryData | StreamedTrajectories]
    device: torch.device


def load_data(config: TrainConfig, resume: bool, world: distributed.World,
              emit: OnEvent, reserved: bool = False) -> RunData:
    """The datasets and their splits, and the config with their absolute paths (so that a
    run can be resumed and evaluated from any folder), resolved for the first (a resumed
    run's config.json is resolved already).

    Raises:
        ValueError, FileNotFoundError: as `mpnode_cli.training.loop.train` says.
    """
    if not resume and not reserved:  # the run folder must be free and writable before any
        # work (every rank refuses together); a reserved one was checked when made
        world.from_main(lambda: runs.check_new(Path(config.run_dir)) if config.run_dir
                        else check_output_folder(runs.default_root()))
    datas = load_datasets(config.datasets, config.stream)
    if not config.allow_predictions:
        check_ground_truth(datas)
    paths = [Path(p).resolve() for p in config.datasets]
    config = config.model_copy(update={"dataset": paths[0] if len(paths) == 1 else paths} | (
        {"init_checkpoint": Path(config.init_checkpoint).resolve()}
        if config.init_checkpoint is not None else {}))
    if not resume:
        config = resolve_train_config(config, datas[0])
        bare = [p for d, p in zip(datas, paths, strict=True) if not d.attrs.get("periodic_states")]
        if config.wrap_angles and bare:  # as `--periodic embed` there is refused
            raise ValueError(f"--wrap-angles: {bare[0]} declares no periodic states (a system's "
                             "periodic_states, or mpnode import --periodic NAME): leave it out")
    longest = max(d.time.numel() for d in datas)  # fixed steps a rollout of them all takes
    check_steps(solver_steps(config.solver, float(datas[0].time[1] - datas[0].time[0]),
                             longest)[0], config.solver)
    device = torch_device(config.device)
    train_sets, val_sets = train_and_validation(datas, config.trajectories)
    if note := fewer_than_asked(datas, train_sets, config.trajectories):
        emit({"event": "warning", "text": note})
    return RunData(config=config, world=world, emit=emit, datas=datas, train_sets=train_sets,
                   val_sets=val_sets, device=device)


def set_up(config: TrainConfig, data: RunData, resume: bool, folder: RunFolder,
           finished_ok: bool) -> Run:
    """Build the model from its starting point, with its normalizer and optimizer; restore
    a resumed run's state; open the run folder (`folder`: a resumed run's checked already).

    Args:
        config: `data.config` with `solver.compile` settled.

    Raises:
        ValueError, FileNotFoundError: as `mpnode_cli.training.loop.train` says.
    """
    world, datas, train_sets = data.world, data.datas, data.train_sets
    last, parent = _starting_point(config, resume, datas, finished_ok, folder.last)
    source, renormalize = last or parent, parent is not None and config.renormalize
    kind, model_config = _architecture(config, source, parent is not None, datas)
    seeds = members_of(config, source, parent is not None)
    model = _build_members(kind, model_config, config.seed, seeds)
    # config.json tells the truth: the architecture is what was built.
    config = config.model_copy(update={"model": kind, "seeds": seeds,
                                       "model_options": model.options.model_dump()})
    # The default name holds the time and whatever suffix makes it new: rank 0 chooses it.
    run_dir = world.from_main(
        lambda: Path(config.run_dir or runs.default_run_dir(config.datasets, kind)))
    config = config.model_copy(update={"run_dir": run_dir})
    normalizer = _normalizer(config, source, renormalize, train_sets)
    # Embedded angles stay in radians: the model takes their sin and cos.
    normalizer = normalizer.unscaled(model.config.get("periodic_dims") or ())
    parent_sha = last.parent_sha256 if last else (
        file_sha256(config.init_checkpoint) if parent else None)

    # The run's precision before any weights load: the model is built in float32, which
    # would round a float64 checkpoint's weights (a float64 resume would then drift).
    model.to(dtype=getattr(torch, config.dtype))
    if source is not None:
        model.load_state_dict(source.state_dict)  # as many members (`members_of`)
    if source is None or renormalize:
        # Statistics of this train split: L2S's one-step differences, PNA's degree δ.
        _fit_statistics(model, train_sets, normalizer)
    model.to(device=data.device, dtype=getattr(torch, config.dtype))
    world.broadcast_module(model)
    # Checkpointed backprop where plain backprop does not fit: config.json says so.
    config = step_memory.check_run(model, config, train_sets, normalizer, data.device, world,
                                   data.emit)
    optimizer = Adam([{"params": list(m.parameters())} for m in model.members], lr=config.lr)
    # Batch order and noise, each member's from its own seed.
    shuffles = [torch.Generator().manual_seed(config.seed + k) for k in range(seeds)]
    state = (LoopState(members=[MemberState() for _ in range(seeds)]) if last is None
             else _restore(last, optimizer, shuffles))
    if not world.main:
        # The only draws from torch's global generator in training are L2S's step noise on
        # each rank's own slice: other ranks must not repeat rank 0's draws.
        torch.manual_seed(hash((config.seed, world.rank, state.epoch)))
    facts = _facts(datas, config.datasets, train_sets)
    if all(lo == hi for lo, hi in facts["train_range"]["states"]):
        data.emit({"event": "warning", "text": "every state component is constant over the "
                   "train split: there is nothing to learn, and every error and baseline "
                   "will be 0; check the data"})
    world.from_main(lambda: folder.open(run_dir, config))
    # Each rank validates its part of each split; the error sums are added over ranks.
    val_parts = [v.select(torch.arange(len(v))[world.shard(len(v))]) for v in data.val_sets]
    return Run(config=config, run_dir=run_dir, world=world, emit=data.emit, datas=datas,
               names=dataset_names(config.datasets), train_sets=train_sets,
               val_parts=val_parts, facts=facts,
               kind=kind, model_config=model.config, model=model, normalizer=normalizer,
               optimizer=optimizer, shuffle=shuffles[0], shuffles=shuffles,
               device=data.device,
               state=state, resumed=last is not None, parent_sha=parent_sha,
               loss_scale=dataset_loss_scale(config.balance_datasets, train_sets,
                                             normalizer))


def _starting_point(config: TrainConfig, resume: bool, datas: list, finished_ok: bool,
                    checked: Checkpoint | None) -> tuple[Checkpoint | None, Checkpoint | None]:
    """`(last, parent)`: the run's `last.pt` (resume; `checked` if rank 0 read it already)
    or the checkpoint a finetune starts from, or neither (fresh weights)."""
    if resume and config.run_dir is None:
        raise ValueError("resume needs the run folder (run_dir)")
    parent = None if resume or config.init_checkpoint is None else load_checkpoint(
        config.init_checkpoint)
    last = checked or (load_checkpoint(runs.checkpoint_path(config.run_dir, "last"))
                       if resume else None)
    if last is not None:
        check_resumable(config, last, datas, finished_ok)
    return last, parent


def _architecture(config: TrainConfig, source: Checkpoint | None, finetune: bool,
                  datas: list) -> tuple[str, dict[str, Any]]:
    """The model's kind and config: the starting point's (checked against every dataset),
    or the config's with the sizes of the data."""
    if source is not None:
        for each in datas:
            check_compatible(source.model_kind, source.model_config,
                             source.dataset["num_nodes"], each,
                             "finetune" if finetune else "resume", source.dataset.get("system"),
                             allow_other_system=config.allow_other_system)
        return source.model_kind, source.model_config
    data = datas[0]
    _check_one_size(config.model, datas)
    options = dict(config.model_options)
    if options.get("periodic") in ("embed", "auto"):
        options |= _periodic(options["periodic"], datas, config.datasets)
    return config.model, {"node_dim": data.node_dim, "control_dim": data.control_dim,
                          "num_nodes": data.num_nodes, **options}


def _periodic(choice: str, datas: list, paths: list[Path]) -> dict[str, Any]:
    """MP-NODE's `periodic` and `periodic_dims` for `--periodic embed` or `auto`: the state
    indices the datasets declare periodic; `auto` resolves to `embed` where they declare
    some and to `off` where none does, so the checkpoint says which ran.

    Raises:
        ValueError: `embed` on a dataset that declares none, or datasets that declare
            different ones.
    """
    from mpnode_cli.data.hdf5 import periodic_dims

    found = [periodic_dims(d.state_names, d.attrs.get("periodic_states") or ())
             for d in datas]
    if choice == "auto" and not any(found):
        return {"periodic": "off"}
    for dims, path in zip(found, paths, strict=True):
        if not dims and choice == "embed":
            raise ValueError(f"--periodic embed: {path} declares no periodic states (a "
                             "system's periodic_states, or mpnode import --periodic NAME)")
        if dims != found[0]:
            raise ValueError(f"--periodic {choice}: {path} declares other periodic states "
                             f"than {paths[0]} (make them agree, or --periodic off)")
    return {"periodic": "embed", "periodic_dims": list(found[0])}


def _build(kind: str, model_config: dict[str, Any]) -> torch.nn.Module:
    try:
        return build_model(kind, model_config)
    except (MemoryError, RuntimeError) as exc:  # torch reports a failed allocation so
        raise ValueError(f"cannot build model '{kind}' with {model_config}: out of memory "
                         f"({str(exc).splitlines()[0][:80]})") from None


def _normalizer(config: TrainConfig, source: Checkpoint | None, renormalize: bool,
                train_sets: list) -> Normalizer:
    """The starting point's normalization, or the z-score of the train splits."""
    if source is not None and not renormalize:
        return source.build_normalizer()
    if config.stream:
        return train_sets[0].fit_normalizer()  # one pass over the file, in blocks
    if len(train_sets) == 1:
        return Normalizer.fit(train_sets[0].states, train_sets[0].controls)
    # Several datasets: on their train splits pooled.
    controls = [t.controls for t in train_sets]
    return Normalizer.fit([t.states for t in train_sets],
                          None if controls[0] is None else controls)


def _restore(last: Checkpoint, optimizer: Adam, shuffles: list[torch.Generator]
             ) -> LoopState:
    """Where a resumed run stopped: its optimizer, RNG states and counters."""
    optimizer.load_state_dict(last.optimizer)
    torch.set_rng_state(last.rng["torch"])
    states = last.rng.get("member_shuffles", last.rng["shuffle"].unsqueeze(0))
    for shuffle, saved in zip(shuffles, states, strict=True):
        shuffle.set_state(saved.clone())
    return LoopState.from_dict(last.loop)


def members_of(config: TrainConfig, source: Checkpoint | None, finetune: bool) -> int:
    """S, the members the run trains: `seeds`; a resumed run's, or a finetuned ensemble's.

    Raises:
        ValueError: a finetune asked for other members than the checkpoint's (`--seeds` 1
            or theirs), or of an ensemble on several datasets.
    """
    have = int(source.model_config.get("members", 1)) if source is not None else 1
    if finetune and have > 1 and len(config.datasets) > 1:
        raise ValueError(f"the checkpoint is an ensemble of {have} members, which trains on "
                         "one dataset: finetune it on one, or export a member (mpnode check "
                         "CKPT --member K --out FILE) and finetune that on several")
    if finetune and config.seeds not in (1, have):
        # Members copied from fewer would start alike: their spread would measure nothing.
        raise ValueError(f"the checkpoint holds {have} member(s), each finetuned from its "
                         f"own weights: give --seeds {have} (or leave it out), not "
                         f"{config.seeds}; an ensemble of new members is train --seeds S")
    return config.seeds if source is None else have


def _build_members(kind: str, model_config: dict[str, Any], seed: int, seeds: int):
    """The ensemble of `seeds` members (a model of one, `ensemble_of`), member k built after
    seeding with seed + k, as a run of that seed alone builds it."""
    from mpnode_cli.models.ensemble import ensemble_of

    config = {k: v for k, v in model_config.items() if k != "members"}
    members = []
    for k in range(seeds):
        torch.manual_seed(seed + k)
        members.append(_build(kind, config))
    return ensemble_of(members)


def _facts(datas: list, paths: list[Path], train_sets: list) -> dict[str, Any]:
    """What a checkpoint records of the training datasets: the first's at the top, where
    readers look; every dataset's under `datasets` when there are several; the training
    range over all of them."""
    facts = _dataset_facts(datas[0], paths[0])
    if len(datas) > 1:
        facts["datasets"] = [_dataset_facts(d, p) for d, p in zip(datas, paths, strict=True)]
    facts["train_range"] = training_range(*train_sets).to_dict()
    return facts


def _dataset_facts(data, path: Path) -> dict[str, Any]:
    return {"fingerprint": data.fingerprint, "path": str(path), "system": data.system,
            "num_nodes": data.num_nodes, "node_dim": data.node_dim,
            "control_dim": data.control_dim, "state_names": list(data.state_names),
            "control_names": list(data.control_names), "topology": data.attrs.get("topology"),
            "periodic_states": list(data.attrs.get("periodic_states") or ())}


def _check_one_size(kind: str, datas: list) -> None:
    """Refuse datasets of several N for a model built for one node count."""
    sizes = sorted({d.num_nodes for d in datas})
    if len(sizes) > 1 and kind in OPTIONS and not model_class(kind).transferable:
        raise ValueError(f"model '{kind}' runs only on graphs of the size it was built for, "
                         f"but the datasets have N = {', '.join(map(str, sizes))}: train it "
                         "on datasets of one N, or choose a model of node dynamics (mpnode)")


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

