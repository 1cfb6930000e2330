"""The neural ODEs' one rollout: integrate a learned vector field from x(t₀).

MP-NODE, GNN-ODE and NODE differ only in their vector field (and MP-NODE in the message
states its ODE state carries after x); everything else about a rollout is written once here,
in `NeuralODEModel.rollout`:

- the states are checked against the model's sizes, and so are the controls: a model with
  U > 0 controls per node refuses a rollout without them or with another U;
- controls act as a zero-order hold (`zoh_controls`), and no solver step may straddle a
  change of the held control (`control_stops` gives the stops);
- the whole horizon is integrated in one adaptive solve (`mpnode_cli.solver.solve`, with the
  training config's `SolverOptions`) from z(t₀) = `initial_state(x0, u0)` (x0, and for
  MP-NODE its initial messages), with dense output at the sample times (float64 `ts`);
  the solve may go on with the trajectories still running only (`SolverOptions.compact`):
  the vector field is rebuilt for them on their graphs and controls (`restrict`), and, for
  an ensemble's stacked members (`members`), with the weights of the members that still
  run (`StackedMembers.kept`);
- the solution `[B, T, N, D+M]` splits into the states (its first D features per node) and
  the message states (the last M, returned when asked for and M > 0).
"""

from __future__ import annotations

import abc
from collections.abc import Callable

import torch

from mpnode_cli.graphs.matrices import EdgeBatch
from mpnode_cli.models.backend import Graph, as_graph
from mpnode_cli.models.base import NeuralModel, Rollout
from mpnode_cli.models.stacked import StackedMembers
from mpnode_cli.solver import solve
from mpnode_cli.solver.options import SolverOptions
from mpnode_cli.solver.runge_kutta import RHS

Control = Callable[[torch.Tensor], torch.Tensor]  # u(t [B]) → [B, N, U]


class NeuralODEModel(NeuralModel):
    """A model whose rollout solves `dz/dt = vector_field(adjacency, u)(t, z)` from z(t₀).

    A subclass defines `vector_field`; one whose ODE state carries M message states per node
    after x also sets `message_dim` and `initial_state`. Its constructor takes the
    arguments of `NeuralModel`.

    Attributes:
        message_dim: M, message states per node after the D state features (0: none).
    """

    message_dim: int = 0

    @abc.abstractmethod
    def vector_field(self, adjacency: Graph, u: Control | None = None) -> RHS:
        """`f(t [B], z [B, N, D+M]) → dz/dt [B, N, D+M]` for `solve`.

        Args:
            adjacency: `[B, N, N]`, `A[b, i, j] ≠ 0` iff node j sends to node i, or an
                `EdgeBatch` (large graphs); a model that does not read the graph ignores it.
            u: `u(t [B]) → [B, N, U]` (zero-order hold), or None when U = 0.
        """

    def initial_state(self, x0: torch.Tensor, u0: torch.Tensor | None) -> torch.Tensor:
        """z(t₀) `[B, N, D+M]` from `x0: [B, N, D]` and the first controls `u0: [B, N, U]`
        (None without controls): x0 itself when there are no message states."""
        return x0

    def rollout(self, x0: torch.Tensor, ts: torch.Tensor, adjacency: Graph,
                controls: torch.Tensor | None = None, *, solver: SolverOptions | None = None,
                return_messages: bool = False, members: StackedMembers | None = None
                ) -> Rollout:
        """Integrate from x(t₀) over the whole horizon.

        Args:
            x0: `[B, N, D]` normalized states at `ts[0]`.
            ts: `[T]` sample times.
            adjacency: `[B, N, N]`, or an `EdgeBatch` (large graphs).
            controls: `[B, T, N, U]` normalized, zero-order hold; required when U > 0
                (ignored when U = 0).
            solver: how to integrate (None: `solve`'s defaults; training passes its
                config's, `TrainConfig.solver`).
            return_messages: also return the message states (None for a model without).
            members: the stacked members this call runs with (an ensemble's rollout under
                `functional_call`, `mpnode_cli.models.ensemble`): the batch is their rows,
                member after member; None: one model's weights.

        Raises:
            ValueError: states of another size than the model's (`check_states`), or
                controls missing or of another U.
        """
        self.check_states(x0)
        ts = ts.to(device=x0.device, dtype=torch.float64)
        u = self._held_controls(controls, ts)
        z0 = self.initial_state(x0, controls[:, 0] if u is not None else None)
        # Steps must not straddle a control switch: stop where the held control changes.
        tstops = control_stops(controls, ts) if u is not None else None
        options = solver.solve_kwargs() if solver is not None else {}
        graph = as_graph(adjacency, x0)
        restrict, block = self._restriction(graph, controls if u is not None else None, ts,
                                            z0.shape[0], members)
        f = self.vector_field(graph, u)
        if members is not None and options.get("checkpoints"):
            # The backward pass reruns steps after the ensemble's `functional_call` has put
            # back this member's own weights: each evaluation binds the members' again.
            f = members.kept(self, torch.arange(members.size, device=z0.device), f)
        sol = solve(f, z0, ts, **options, tstops=tstops, restrict=restrict,
                    restrict_block=block)
        d = self.node_dim
        messages = sol.ys[..., d:] if return_messages and self.message_dim else None
        return Rollout(states=sol.ys[..., :d], messages=messages, status=sol.status,
                       n_f_evals=int(sol.stats["n_f_evals"].max()))

    def _restriction(self, graph: Graph, controls: torch.Tensor | None, ts: torch.Tensor,
                     batch: int, members: StackedMembers | None
                     ) -> tuple[Callable[[torch.Tensor], RHS] | None, int]:
        """`solve`'s `restrict` and `restrict_block` for compaction: the vector field of
        some of the batch's trajectories, on their graphs and controls.

        With stacked `members` the batch is their rows one member after another, which the
        stacked layers line up with the members' weights; so trajectories are kept by whole
        members (blocks of `batch / S`) and the field runs with the kept members' weights
        (`StackedMembers.kept`).

        Args:
            graph: `[B, N, N]` (or `[1, N, N]`) or an `EdgeBatch`, as `vector_field` takes it.
            controls: `[B, T, N, U]`, or None for a model without controls.
            ts: `[T]` float64; batch: B.
            members: the stacked members the rollout runs with, or None (one model).

        Returns:
            `(restrict, block)`; restrict None (no compaction) in an ensemble rollout whose
            batch is not whole members.
        """
        block = 1
        if members is not None:
            if batch % members.size:
                return None, 1
            block = batch // members.size

        def restrict(index: torch.Tensor) -> RHS:
            u = None if controls is None else zoh_controls(controls[index], ts)
            f = self.vector_field(select_graphs(graph, index), u)
            if members is None:
                return f
            kept = index.view(-1, block)[:, 0] // block  # whole members, in order
            return members.kept(self, kept, f)  # the field runs with those members' weights

        return restrict, block

    def _held_controls(self, controls: torch.Tensor | None, ts: torch.Tensor) -> Control | None:
        """u(t) for `controls: [B, T, N, U]`, or None for a model without controls.

        Raises:
            ValueError: the model takes U > 0 controls and `controls` is None or of another U.
        """
        if not self.control_dim:
            return None
        if controls is None or controls.shape[-1] != self.control_dim:
            got = "none" if controls is None else f"{controls.shape[-1]}"
            raise ValueError(f"the model expects {self.control_dim} controls per node, got "
                             f"{got}: give the controls its training data had")
        return zoh_controls(controls, ts)


def zoh_controls(controls: torch.Tensor, ts: torch.Tensor) -> Control:
    """u(t) for a zero-order hold: `controls[:, k]` acts on `[ts[k], ts[k+1])`.

    Args:
        controls: `[B, T, N, U]`; ts: `[T]` float64.

    Returns:
        `u(t: [B]) -> [B, N, U]`.
    """
    rows = torch.arange(controls.shape[0], device=controls.device)
    last = ts.numel() - 2  # the last sample's control is never held over an interval

    def u(t: torch.Tensor) -> torch.Tensor:
        k = (torch.searchsorted(ts, t.contiguous(), right=True) - 1).clamp(0, max(last, 0))
        return controls[rows, k]

    return u


def select_graphs(graph: Graph, index: torch.Tensor) -> Graph:
    """The graphs of the trajectories `index` (`[B']` int64) of `graph` (`[B, N, N]` or an
    `EdgeBatch`); one graph shared by the batch (`[1, N, N]`, or an `EdgeBatch` of B = 1)
    stays shared."""
    if isinstance(graph, EdgeBatch):
        return graph if graph.batch == 1 else graph.take(index)
    return graph if graph.shape[0] == 1 else graph.index_select(0, index)


def control_stops(controls: torch.Tensor | None, ts: torch.Tensor) -> torch.Tensor | None:
    """The solver's `tstops` for zero-order-hold controls: the sample times where they change.

    A step must not straddle a change of u(t) (the RK stages would mix two inputs), but
    where the held control stays the same a stop would only cost steps: a constant input
    (a per-node power injection) then integrates like an autonomous system. One stop list
    serves the whole batch, so a time is a stop when any trajectory's control changes there.

    Args:
        controls: `[B, T, N, U]` (as `zoh_controls` holds them), or None.
        ts: `[T]` sample times, on the controls' device.

    Returns:
        `[S]` the times `ts[k]`, 0 < k < T − 1, where `controls[:, k] != controls[:, k-1]`
        for some trajectory, node or component (the last sample's control is never held);
        None when there are none.
    """
    if controls is None or ts.numel() < 3:
        return None
    held = controls[:, : ts.numel() - 1]  # (B, T-1, N, U): the controls that act
    changed = (held[:, 1:] != held[:, :-1]).flatten(2).any(dim=2).any(dim=0)  # (T-2,)
    stops = ts[1:-1][changed]
    return stops if stops.numel() else None
