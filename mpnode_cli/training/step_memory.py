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

A neural ODE's whole rollout, whose graph may itself not fit, is measured in parts, so
that the measuring never takes the memory it measures: the bytes saved per evaluation of f
on a short solve (the first samples, at most `_PROBE_STEPS` solver steps, and never more
bytes than the run may take: `_Full`), times the evaluations of the whole horizon, counted
without gradients. A horizon the solver cannot finish in `max_steps` (a time scale far
from the model's) is refused there: every batch would end unfinished.
Where the plain step passes what a `--memory-budget` (or the free memory) leaves, the run
backpropagates through checkpointed solves (`SolverOptions.checkpoints`).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from typing import Any, NamedTuple

import torch

from mpnode_cli.memory import available_memory, format_bytes, parse_size
from mpnode_cli.solver.options import SolverOptions
from mpnode_cli.training.memory_guard import CHECKPOINTS, resident_bytes

ADVICE = ("lower --batch-size or --seeds, or train on shorter trajectories, smaller graphs or "
          "a machine with more memory")
_PROBE_SAMPLES = 3  # the samples whose rollout measures the bytes saved per evaluation
_PROBE_STEPS = 64  # its most solver steps (bytes per evaluation within 1% of a whole solve's)
_STEP_EVALS = 7  # evaluations of f whose graph one rerun step holds (Tsit5's 7 stages)
# A checkpointed solve's own bytes per evaluation of f: each step's autograd node and its
# host-side arguments (3.5 kB a step of 6 evaluations: docs/solver.md).
_NODE_BYTES = 1024
# The fewest states a run is switched to: fewer would rerun each step many times.
_LEAST_STATES = 8


class StepNeed(NamedTuple):
    """The bytes a training step keeps at least: `plain`, backpropagating through every
    solver step; checkpointed with C states, `step + C × state` (step inf: no solver)."""

    plain: float
    step: float
    state: float


def saved_bytes(model: torch.nn.Module, x: torch.Tensor, ts: torch.Tensor, graph: Any,
                u: torch.Tensor | None, solver: Any) -> int:
    """Bytes of the distinct storages autograd saves for the backward pass of one training
    loss: every member of `model` on the same trajectories `x: [B, H, N, D]` (controls `u`),
    over `ts: [H]` and `graph`, solved with `solver`. Torch's global random state is left
    as it was (L2S draws its training noise from it)."""
    return _measure(model, x, ts, graph, u, solver)[0]


class _Full(Exception):
    """The bytes a measurement saved passed the most it may take."""


def _measure(model: torch.nn.Module, x: torch.Tensor, ts: torch.Tensor, graph: Any,
             u: torch.Tensor | None, solver: Any, cap: float = math.inf
             ) -> tuple[int, int, bool]:
    """`(saved_bytes, evaluations of f, finished)` of that training loss (its slowest
    member's; finished: every member's solve reached `ts[-1]`).

    Raises:
        _Full: the saved bytes passed `cap` (what was saved is freed).
    """
    storages: dict[tuple[int, int], int] = {}
    total = [0]

    def pack(t: torch.Tensor) -> torch.Tensor:
        s = t.untyped_storage()
        key = (s.data_ptr(), t.device.index or 0)
        if key not in storages:
            storages[key] = s.nbytes()
            total[0] += s.nbytes()
            if total[0] > cap:
                raise _Full
        return t

    members = len(model.members)
    xs = x.expand(members, *x.shape)  # (S, B, H, N, D): one view, no copies
    us = None if u is None else u.expand(members, *u.shape)
    devices = [x.device] if x.device.type == "cuda" else []
    with torch.random.fork_rng(devices=devices), \
            torch.autograd.graph.saved_tensors_hooks(pack, lambda t: t):
        losses = model.training_losses(xs, ts, [graph] * members, us, _squared_error,
                                       range(members), solver=solver)
    evals = max(loss.n_f_evals for loss in losses)
    finished = all(bool((loss.status == 0).all()) for loss in losses)
    del losses  # frees the graph the hooks counted
    return sum(storages.values()), evals, finished


def batch_need(model: torch.nn.Module, x: torch.Tensor, ts: torch.Tensor, graph: Any,
               u: torch.Tensor | None, solver: Any, batch: int,
               room: float | None = None) -> StepNeed:
    """The `StepNeed` of `batch` trajectories like `x: [1, H, N, D]` over `ts: [H]` (as
    `saved_bytes`): a model without solver measured whole; a neural ODE by the bytes saved
    per evaluation of f on a short solve of the first samples and the evaluations of a
    whole rollout (`_horizon_evals`). No measurement saves more than `room` bytes: where
    even one solver step of one trajectory would, the need is infinite."""
    solver = solver if solver is not None else SolverOptions()
    cap = math.inf if room is None else room
    evals = _horizon_evals(model, x, ts, graph, u, solver)
    if not evals:
        try:
            return StepNeed(batch * _measure(model, x, ts, graph, u, solver, cap)[0],
                            math.inf, 0)
        except _Full:
            return StepNeed(math.inf, math.inf, 0)
    k = min(_PROBE_SAMPLES, ts.numel())
    # One step (what a checkpointed rerun keeps) where those do not fit in `room`: its
    # per-evaluation bytes carry the solve's fixed cost, about a third more.
    for steps in (_PROBE_STEPS, 1):
        short = solver.model_copy(update={"max_steps": min(steps, solver.max_steps)})
        try:
            saved, probed, _ = _measure(model, x[:, :k], ts[:k], graph,
                                        None if u is None else u[:, :k], short, cap)
            break
        except _Full:
            continue
    else:
        return StepNeed(math.inf, math.inf, math.inf)
    per_eval = saved / max(probed, 1)
    member = model.members[0]
    y = (len(model.members) * x.shape[-2] * x.element_size()  # one state y, every member
         * (member.node_dim + getattr(member, "message_dim", 0)))
    # One rerun step's graph, the outputs (one y per sample) and the loss's difference of
    # them; each kept state holds y and k₁.
    step = per_eval * _STEP_EVALS + 2 * ts.numel() * y
    return StepNeed(batch * per_eval * evals, batch * step + evals * _NODE_BYTES, batch * 2 * y)


def _horizon_evals(model: torch.nn.Module, x: torch.Tensor, ts: torch.Tensor, graph: Any,
                   u: torch.Tensor | None, solver: Any) -> int:
    """The evaluations of f a rollout of `x` over all of `ts` takes, counted without
    gradients (the memory of a rollout's output alone), in at most `solver.max_steps`
    steps, as a training step's own solve.

    Raises:
        ValueError: one line, where the solve does not finish in them: at the initial
            weights every training batch would end unfinished.
    """
    with torch.no_grad():
        _, evals, finished = _measure(model, x, ts, graph, u, solver)
    if not finished:
        raise ValueError(
            f"at its initial weights the model's solve of one training trajectory does "
            f"not finish its horizon (t {float(ts[0]):g} to {float(ts[-1]):g}) in "
            f"--max-steps {solver.max_steps} solver steps: every batch would end "
            "unfinished; train on shorter trajectories or on data sampled on another time "
            "scale (a smaller dt), or raise --max-steps")
    return evals


def _squared_error(pred: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """What any training loss keeps of the rollout: its difference from the target."""
    return (pred - target).square().mean()


def step_need(model: torch.nn.Module, train_sets: Sequence, normalize: Any, dtype: torch.dtype,
              device: torch.device, solver: Any, batch: int, room: float | None = None
              ) -> StepNeed:
    """The bytes a training step of `batch` trajectories (this rank's share) will keep at
    least: the largest over `train_sets` of `batch` × one trajectory's over the dataset's
    whole horizon (`batch_need`, measuring in at most `room` bytes). `normalize` maps raw
    states to the model's (the run's `Normalizer`)."""
    needs = [StepNeed(0, 0, 0)]
    for data in train_sets:
        one = data.take(torch.arange(min(1, len(data))))
        if not len(one):
            continue
        x = normalize.norm_x(one.states).to(device, dtype)
        u = None if one.controls is None else normalize.norm_u(one.controls).to(device, dtype)
        needs.append(batch_need(model, x, data.time.to(device), one.graph(device), u, solver,
                                min(batch, len(data)), room))
    return StepNeed(*(max(v) for v in zip(*needs, strict=True)))


def budget_room(budget: str | None) -> int | None:
    """The bytes a training step may take: what this process may still allocate
    (`available_memory`), and within a `--memory-budget` (all the process holds) what is
    left of it; None where neither is known."""
    have = available_memory()
    if budget is None:
        return have
    left = max(parse_size(budget) - (resident_bytes() or 0), 0)
    return left if have is None else min(have, left)


def _states_that_fit(need: StepNeed, room: int) -> int:
    """The most states, up to `CHECKPOINTS`, that a checkpointed step keeps in `room`."""
    if not math.isfinite(need.step) or need.step >= room:
        return 0
    return int(min(CHECKPOINTS, (room - need.step) // max(need.state, 1)))


def per_rank_batch(batch_size: int, ranks: int) -> int:
    """The most trajectories a rank takes from a global batch (`World.shard`'s split)."""
    return math.ceil(batch_size / ranks)


def check_run(model: torch.nn.Module, config: Any, train_sets: Sequence, normalize: Any,
              device: torch.device, world: Any, emit: Callable[[dict], None]) -> Any:
    """The run's config (`config`: its `TrainConfig`) with the backprop its training step
    fits in (`budget_room`): as it is where plain backprop fits, or the run checkpoints
    already (a resumed run goes on as it began); else checkpointed, with as many states as
    fit up to `CHECKPOINTS`, said in one warning (`emit`). Every rank takes the largest
    need, so all decide alike.

    Raises:
        ValueError: one line, before the run folder is touched, where even that cannot fit.
    """
    batch = per_rank_batch(config.batch_size, world.size)
    # Measured uncompiled: a compiled step would compile here for this one trajectory (tens
    # of seconds on a CPU) and once more for the run's own batch. And without checkpoints,
    # whose steps save nothing to count.
    solver = config.solver.model_copy(update={"compile": False, "checkpoints": None})
    # The measuring itself never takes more than this process may still allocate.
    need = step_need(model, train_sets, normalize, getattr(torch, config.dtype), device,
                     solver, batch, available_memory())
    need = StepNeed(*world.max(torch.tensor(need, dtype=torch.float64)).tolist())
    room, c = budget_room(config.memory_budget), config.solver.checkpoints
    if room is None or (c is None and need.plain <= room):
        return config
    fits = c or _states_that_fit(need, room)
    least = min(need.plain, need.step + _LEAST_STATES * need.state)
    where = "available" if config.memory_budget is None else (
        f"--memory-budget {config.memory_budget} leaves")
    if fits < (c or _LEAST_STATES) or need.step + fits * need.state > room:
        members = len(model.members)
        # Infinite: one solver step of one trajectory saved more than the room (`_Full`).
        least = least if math.isfinite(least) else room
        raise ValueError(
            f"a training step needs at least {format_bytes(least)} of memory (members "
            f"{members} × {batch} trajectories over the whole horizon, "
            f"measured on one{', checkpointed' if least < need.plain else ''}), more than "
            f"the {format_bytes(room)} {where}: "
            f"{'raise --memory-budget, or ' * (config.memory_budget is not None)}{ADVICE}")
    if c is None:
        emit({"event": "warning", "text": f"a training step needs about "
              f"{format_bytes(need.plain)} with plain backprop, more than the "
              f"{format_bytes(room)} {where}: it backpropagates through checkpointed solves "
              f"({fits} stored states, about {format_bytes(need.step + fits * need.state)}; "
              "the same gradient, 1.5–2× the time)"})
    return config.model_copy(update={"solver": config.solver.model_copy(
        update={"checkpoints": fits})})
