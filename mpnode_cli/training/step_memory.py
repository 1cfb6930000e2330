"""The memory a training step will hold, measured before the first step, and a run refused
in one line where it cannot fit.

A step rolls out B trajectories of every member over the horizon and keeps, for the
backward pass, what autograd saves at each right-hand-side evaluation of each solver
stage. Nothing else in training grows like it: the weights, Adam's moments and a
validation batch (rolled out without gradients) are small beside it. How much that is
depends on the model, the graph, the horizon and how many steps the adaptive solver takes,
none of which a formula knows ahead. So it is measured: one trajectory of each training
dataset, every member, over the longest horizon the run will use (the horizon curriculum's
last), rolled out as a step does it, with `torch.autograd.graph.saved_tensors_hooks`
counting the bytes of every distinct storage autograd keeps. A step needs about B times
that.

That is a floor, not the peak: the backward pass adds its own temporaries, and another
batch may take more solver steps than the one measured. A run is refused only when even
the floor exceeds what this process may still take (`mpnode_cli.memory.available_memory`),
so a refusal is certain and a run that fits is never refused; a run near the line may
still fail in its step, where `mpnode_cli.memory.naming_memory` names it. The probe runs
uncompiled, whatever the run's `solver.compile` (compiling it would cost a CPU tens of
seconds for one trajectory): for a compiled run it is the floor of the eager step, which
the run falls back to if its compile fails.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

import torch

from mpnode_cli.memory import available_memory, format_bytes

ADVICE = ("lower --batch-size or --seeds, or train on shorter trajectories, smaller graphs or "
          "a machine with more memory")


def saved_bytes(model: torch.nn.Module, x: torch.Tensor, ts: torch.Tensor, graph: Any,
                u: torch.Tensor | None, solver: Any) -> int:
    """Bytes of the distinct storages autograd saves for the backward pass of one training
    loss: every member of `model` on the same trajectories `x: [B, H, N, D]` (controls `u`),
    over `ts: [H]` and `graph`, solved with `solver`. Torch's global random state is left
    as it was (L2S draws its training noise from it)."""
    storages: dict[tuple[int, int], int] = {}

    def pack(t: torch.Tensor) -> torch.Tensor:
        s = t.untyped_storage()
        storages[(s.data_ptr(), t.device.index or 0)] = s.nbytes()
        return t

    members = len(model.members)
    xs = x.expand(members, *x.shape)  # (S, B, H, N, D): one view, no copies
    us = None if u is None else u.expand(members, *u.shape)
    devices = [x.device] if x.device.type == "cuda" else []
    with torch.random.fork_rng(devices=devices), \
            torch.autograd.graph.saved_tensors_hooks(pack, lambda t: t):
        losses = model.training_losses(xs, ts, [graph] * members, us, _squared_error,
                                       range(members), solver=solver)
    del losses  # frees the graph the hooks counted
    return sum(storages.values())


def _squared_error(pred: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """What any training loss keeps of the rollout: its difference from the target."""
    return (pred - target).square().mean()


def step_need(model: torch.nn.Module, train_sets: Sequence, normalize: Any, dtype: torch.dtype,
              device: torch.device, solver: Any, batch: int) -> int:
    """The bytes a training step of `batch` trajectories (this rank's share) will keep at
    least: the largest over `train_sets` of `batch` × the bytes saved for one trajectory
    over the dataset's whole horizon (`saved_bytes`). `normalize` maps raw states to the
    model's (the run's `Normalizer`)."""
    need = 0
    for data in train_sets:
        one = data.take(torch.arange(min(1, len(data))))
        if not len(one):
            continue
        x = normalize.norm_x(one.states).to(device, dtype)
        u = None if one.controls is None else normalize.norm_u(one.controls).to(device, dtype)
        ts = data.time.to(device)
        per = saved_bytes(model, x, ts, one.graph(device), u, solver)
        need = max(need, per * min(batch, len(data)))
    return need


def check_step_memory(need: int, batch: int, members: int) -> None:
    """Refuse a run whose step will keep more than this process may still take.

    Raises:
        ValueError: one line with the need, what is available and what to lower.
    """
    have = available_memory()
    if have is None or need <= have:
        return
    raise ValueError(
        f"a training step needs at least {format_bytes(need)} of memory ({members} "
        f"member{'s' * (members != 1)} × {batch} trajectories over the whole horizon, "
        f"measured on one), more than the {format_bytes(have)} available: {ADVICE}")


def per_rank_batch(batch_size: int, ranks: int) -> int:
    """The most trajectories a rank takes from a global batch (`World.shard`'s split)."""
    return math.ceil(batch_size / ranks)


def check_run(model: torch.nn.Module, config: Any, train_sets: Sequence, normalize: Any,
              device: torch.device, world: Any) -> None:
    """Refuse, before its run folder is touched, a run (`config`: its `TrainConfig`) whose
    training step cannot fit in memory; every rank (`world`) takes the largest need, so
    all refuse together.

    Raises:
        ValueError: one line (`check_step_memory`).
    """
    batch = per_rank_batch(config.batch_size, world.size)
    # Measured uncompiled: a compiled step would compile here for this one trajectory (tens
    # of seconds on a CPU) and once more for the run's own batch.
    solver = config.solver.model_copy(update={"compile": False})
    need = step_need(model, train_sets, normalize, getattr(torch, config.dtype), device,
                     solver, batch)
    need = int(world.max(torch.tensor([need], dtype=torch.float64))[0])
    check_step_memory(need, batch, len(model.members))
