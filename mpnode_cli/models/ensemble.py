"""Ensembles: S members of one architecture, trained and rolled out together.

Each member is an ordinary model with its own weights (its own seed). A neural ODE's members
are integrated in ONE solve: their trajectories are stacked member after member into a
batch of S·B samples, and each layer applies member k's weights to member k's rows as one
batched matmul (`torch.baddbmm` over `[S, rows, in]`). The solver already steps, accepts and
rejects every sample on its own, so a member's rows follow exactly the steps they would
take alone; the members share only the solver's per-step overhead and the kernel launches,
which is what makes S members cheaper than S runs (`bench/ensemble.py` measures it).

How a member's weights reach its rows without a second copy of every model: the members'
parameters are stacked (`[S, ...]`, differentiable, so gradients flow back to each member's
own tensors) and swapped into one member for the call (`torch.func.functional_call`); the
models' layers (`mpnode_cli.models.stacked`) see a stacked weight and apply each member's
to its rows. The rollout is given the stacked members explicitly (`StackedMembers`), so
that a solve that compacts can re-bind the weights of the members still running.
Everything else a model does (concatenation, activations, the aggregation over each
sample's graph) acts row by row already.

Models that are not neural ODEs (L2S, whose training is one-step and whose rollout is
autoregressive with its own noise) run their members one after another, each exactly as it
would alone.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import torch
from torch import nn
from torch.func import functional_call

from mpnode_cli.graphs.matrices import EdgeBatch
from mpnode_cli.models.base import BatchLoss, NeuralModel, Rollout
from mpnode_cli.models.stacked import StackedMembers
from mpnode_cli.solver.options import SolverOptions

Graph = torch.Tensor | EdgeBatch


class _Call(nn.Module):
    """Calls one of `model`'s methods as `forward`, for `functional_call`."""

    def __init__(self, model: nn.Module, method: str):
        super().__init__()
        self.model, self.method = model, method

    def forward(self, *args, **kwargs):
        return getattr(self.model, self.method)(*args, **kwargs)


def stack_graphs(graphs: Sequence[Graph]) -> Graph:
    """The graphs of several batches, one after another: `[ΣB, N, N]`, or one `EdgeBatch`
    whose trajectories are the batches' in order."""
    if not isinstance(graphs[0], EdgeBatch):
        widest = max(g.shape[0] for g in graphs)
        return torch.cat([g.expand(widest, *g.shape[1:]) if g.shape[0] == 1 else g
                          for g in graphs])
    senders, receivers, offsets, index, shift = [], [], [graphs[0].offsets[:1]], [], 0
    for g in graphs:
        senders.append(g.senders)
        receivers.append(g.receivers)
        offsets.append(g.offsets[1:] + offsets[-1][-1])
        index.append(g.graph_index + shift)
        shift += g.offsets.numel() - 1
    return EdgeBatch(torch.cat(senders), torch.cat(receivers), torch.cat(offsets),
                     torch.cat(index), graphs[0].num_nodes)


@dataclass
class EnsembleRollout(Rollout):
    """An ensemble's rollout: `states` is the members' mean, `members` each member's.

    Attributes:
        members: `[S, B, T, N, D]` each member's predicted states.
        member_status: `[S, B]` each member's solver status (`status` is the worst).
    """

    # Fields in place of `Rollout`'s properties of one member (always given).
    members: torch.Tensor = None  # type: ignore[assignment]
    member_status: torch.Tensor = None  # type: ignore[assignment]


class Ensemble(NeuralModel):
    """S models of one kind and config, each with its own weights.

    Args:
        members: the models (at least two), built with the same kind and config.

    The ensemble is a `NeuralModel` of its members' kind, sizes and options: `rollout`
    returns the members' mean, with each member's trajectories and their spread beside it
    (`EnsembleRollout`). Training uses `training_losses`, one loss per member on the
    member's own batch (a single model is the ensemble of one, `NeuralModel.members`).
    """

    def __init__(self, members: Sequence[NeuralModel]):
        if len(members) < 2:
            raise ValueError("an ensemble needs at least two members")
        kinds = {(m.kind, repr(sorted(m.config.items()))) for m in members}
        if len(kinds) != 1:
            raise ValueError("an ensemble's members must share one kind and config")
        first = members[0]
        # The contract's class attributes are the members' kind's (one for all of them).
        self.kind, self.Options = first.kind, first.Options
        self.transferable = first.transferable
        self.statistics_need_states = first.statistics_need_states
        self._initial_states = first.initial_states
        super().__init__(first.node_dim, first.control_dim, first.num_nodes, first.options)
        self.members = nn.ModuleList(members)  # a submodule: the `members.k.` weights

    @property
    def members(self) -> nn.ModuleList:
        """The S members."""
        return self._modules["members"]

    @property
    def initial_states(self) -> int:
        return self._initial_states

    @property
    def config(self) -> dict[str, Any]:
        """The members' one config (a model kind may add to the sizes and options, as
        MP-NODE's `periodic_dims`), with `members`: S (what `build_model` reads back)."""
        return self.members[0].config | {"members": len(self.members)}

    def member_prefix(self, k: int) -> str:
        return f"members.{k}."

    @property
    def stackable(self) -> bool:
        """Whether the members integrate in one solve: neural ODEs do."""
        from mpnode_cli.models.ode import NeuralODEModel

        return isinstance(self.members[0], NeuralODEModel)

    def fit_statistics(self, states, dt: float, adjacency) -> None:
        for member in self.members:
            member.fit_statistics(states, dt, adjacency)

    def _stacked(self, active: Sequence[int]) -> StackedMembers:
        """The active members' parameters, each stacked `[S', ...]` (differentiable)."""
        params = [dict(self.members[k].named_parameters()) for k in active]
        return StackedMembers({name: torch.stack([p[name] for p in params])
                               for name in params[0]})

    def member_rollouts(self, x0: torch.Tensor, ts: torch.Tensor, graphs: Sequence[Graph],
                        controls: torch.Tensor | None, active: Sequence[int], *,
                        solver: SolverOptions | None = None, return_messages: bool = False,
                        history: torch.Tensor | None = None) -> list[Rollout]:
        """Each active member's rollout from its own batch.

        Args:
            x0: `[S', B, N, D]` member k's start states in row k of `active`.
            ts: `[T]`.
            graphs: S' graphs, each `[B, N, N]` (or `[1, N, N]`) or an `EdgeBatch`.
            controls: `[S', B, T, N, U]` or None.
            active: the members to roll out (S' of them, in this order).
            solver, return_messages: as `NeuralModel.rollout`.
            history: `[S', B, C, N, D]` for models that start from several states.

        Returns:
            One `Rollout` per active member.
        """
        options = {"solver": solver, "return_messages": return_messages}
        if not self.stackable:
            return [self.members[k].rollout(
                x0[i], ts, graphs[i], None if controls is None else controls[i], **options,
                **({"history": history[i]} if history is not None else {}))
                for i, k in enumerate(active)]
        s, b = x0.shape[0], x0.shape[1]
        flat = x0.flatten(0, 1)  # (S'·B, N, D)
        u = None if controls is None else controls.flatten(0, 1)  # (S'·B, T, N, U)
        template = _Call(self.members[active[0]], "rollout")
        stacked = self._stacked(active)
        out = functional_call(template, {"model." + n: w for n, w in stacked.weights.items()},
                              (flat, ts, stack_graphs(graphs), u),
                              options | {"members": stacked})
        return [Rollout(states=states, status=status,
                        messages=None if out.messages is None else messages,
                        n_f_evals=out.n_f_evals)
                for states, status, messages in zip(
                    out.states.unflatten(0, (s, b)), out.status.view(s, b),
                    (out.messages.unflatten(0, (s, b)) if out.messages is not None
                     else [None] * s), strict=True)]

    def rollout(self, x0: torch.Tensor, ts: torch.Tensor, adjacency: Graph,
                controls: torch.Tensor | None = None, *, solver: SolverOptions | None = None,
                return_messages: bool = False, **extra: Any) -> EnsembleRollout:
        """Every member from the same `x0: [B, N, D]`: the members' mean, and each member.

        Same arguments as `NeuralModel.rollout`; `messages` are the first member's.
        """
        s = len(self.members)
        history = extra.get("history")
        outs = self.member_rollouts(
            x0.expand(s, *x0.shape), ts, [adjacency] * s,
            None if controls is None else controls.expand(s, *controls.shape),
            range(s), solver=solver, return_messages=return_messages,
            history=None if history is None else history.expand(s, *history.shape))
        members = torch.stack([o.states for o in outs])  # (S, B, T, N, D)
        status = torch.stack([o.status for o in outs])  # (S, B)
        return EnsembleRollout(states=members.mean(dim=0), messages=outs[0].messages,
                               status=status.max(dim=0).values,
                               n_f_evals=max(o.n_f_evals for o in outs), members=members,
                               member_status=status)

    def training_loss(self, *args: Any, **kwargs: Any) -> BatchLoss:
        """Refused: each member trains on its own batch (`training_losses`), never the
        members' mean on one."""
        raise TypeError("an ensemble's members train each on its own batch: training_losses")

    def training_losses(self, xs: torch.Tensor, ts: torch.Tensor, graphs: Sequence[Graph],
                        controls: torch.Tensor | None,
                        loss_fn: Callable[[torch.Tensor, torch.Tensor], torch.Tensor],
                        active: Sequence[int], solver: SolverOptions | None = None
                        ) -> list[BatchLoss]:
        """Each active member's training loss on its own batch.

        Args:
            xs: `[S', B, H, N, D]` normalized (noisy) states, member k's batch in row k of
                `active`. ts: `[H]`. graphs: S' batches' graphs. controls: `[S', B, H, N, U]`
                or None. loss_fn, solver: as `NeuralModel.training_loss`.
        """
        if not self.stackable:
            return [self.members[k].training_loss(
                xs[i], ts, graphs[i], None if controls is None else controls[i], loss_fn,
                solver=solver) for i, k in enumerate(active)]
        c = self.initial_states
        outs = self.member_rollouts(
            xs[:, :, 0], ts, graphs, controls, active, solver=solver,
            history=xs[:, :, :c] if c > 1 else None)
        return [BatchLoss(loss_fn(o.states, x) if bool((o.status == 0).all()) else None,
                          o.status, o.n_f_evals) for o, x in zip(outs, xs, strict=True)]


def ensemble_of(members: Sequence[NeuralModel]) -> NeuralModel:
    """`members` as one model: the one model itself (its own ensemble of one), or the
    `Ensemble` of several. The one place that tells one member from several."""
    return members[0] if len(members) == 1 else Ensemble(members)


def spread_error_correlation(spread: torch.Tensor, error: torch.Tensor) -> float:
    """Pearson correlation over trajectories of the members' spread and the actual error.

    Args:
        spread: `[K]` each trajectory's mean members' std. error: `[K]` its RMSE.

    Returns:
        The correlation; NaN for fewer than 3 trajectories or a constant input.
    """
    if spread.numel() < 3:
        return float("nan")
    a, b = spread.double() - spread.double().mean(), error.double() - error.double().mean()
    denom = (a.square().sum() * b.square().sum()).sqrt()
    return float((a * b).sum() / denom) if denom > 0 else float("nan")
