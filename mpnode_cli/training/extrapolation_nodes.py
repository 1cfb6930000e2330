"""Each node of each trajectory against a model's training range: `node_extrapolation`.

Which nodes of which trajectories have states (true states for evaluate and zeroshot,
predicted ones for simulate) or in-degrees outside the range (`TrainRange`), and how far,
so that a user can tell which predictions to trust; `simulate` stores it as the per-node
flags `extrapolation [K, N]` (`STATE_OUTSIDE`, `IN_DEGREE_OUTSIDE`) in its output file.
The report as a whole is `mpnode_cli.training.extrapolation`'s.
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch

from mpnode_cli.training.train_range import TrainRange

# The bits of a node's flag in `NodeExtrapolation.flags` (simulate's `extrapolation [K, N]`).
STATE_OUTSIDE = 1  # bit 0: a state component left its training range at some sample
IN_DEGREE_OUTSIDE = 2  # bit 1: the node's in-degree lies outside the training in-degrees
# The worst nodes a report lists.
WORST = 5
# Predicted states within this many range widths of the range count as inside: a model's
# rollout returns x0 through its float32 normalization and back, a few ulps off.
PREDICTED_SLACK = 1e-6
# Values per block of trajectories when states are compared (8 MiB of float64).
_BLOCK_VALUES = 2**20


@dataclass(frozen=True, eq=False)
class NodeExtrapolation:
    """Each node of each trajectory against a model's training range.

    Attributes:
        in_degree: int64 `[K, N]` each node's in-degree in its trajectory's graph.
        graph_index: int64 `[K]` each trajectory's graph.
        trajectory: int64 `[K]` each trajectory's index where the user finds it (its row
            in the dataset file; in simulate's x0 and output).
        train_in_degree: `(lo, hi)` the in-degrees of training.
        how_far: float64 `[K, N]` how far the node's states leave the training range: the
            largest, over its samples and state components, of the distance outside the
            component's `[lo, hi]` in units of its width `hi − lo` (of 1, in physical
            units, for a component that never varied in training); 0 inside (predicted
            states: within `PREDICTED_SLACK`). None when no states were compared.
        component: int64 `[K, N]` the component of that largest distance (−1 inside), or
            None.
        compared: the states compared: "true", "predicted" (simulate), or None.
        outside_fraction: the fraction of every compared state value (trajectory, time,
            node, component) outside its component's range; None without states.
        state_names: `[D]` the components' names.
    """

    in_degree: np.ndarray
    graph_index: np.ndarray
    trajectory: np.ndarray
    train_in_degree: tuple[int, int]
    how_far: np.ndarray | None
    component: np.ndarray | None
    compared: str | None
    outside_fraction: float | None
    state_names: tuple[str, ...]

    @property
    def state_outside(self) -> np.ndarray:
        """bool `[K, N]`: a state left its training range at some sample."""
        if self.how_far is None:
            return np.zeros(self.in_degree.shape, dtype=bool)
        return self.how_far > 0

    @property
    def degree_outside(self) -> np.ndarray:
        """bool `[K, N]`: the in-degree lies outside the training in-degrees."""
        lo, hi = self.train_in_degree
        return (self.in_degree < lo) | (self.in_degree > hi)

    @property
    def flags(self) -> np.ndarray:
        """uint8 `[K, N]`: `STATE_OUTSIDE` and `IN_DEGREE_OUTSIDE` bits (0: inside)."""
        return (self.state_outside * STATE_OUTSIDE
                | self.degree_outside * IN_DEGREE_OUTSIDE).astype(np.uint8)

    def worst(self, count: int = WORST) -> np.ndarray:
        """int64 `[≤ count]` the flat indices `k · N + n` of the flagged nodes furthest out:
        by `how_far`, then by how far the in-degree lies outside, then in order."""
        flagged = np.flatnonzero(self.flags)
        far = (np.zeros(len(flagged)) if self.how_far is None
               else self.how_far.reshape(-1)[flagged])
        degree = self.in_degree.reshape(-1)[flagged]
        lo, hi = self.train_in_degree
        beyond = np.maximum(np.maximum(lo - degree, degree - hi), 0)
        return flagged[np.lexsort((flagged, -beyond, -far))[:count]]

    def to_dict(self) -> dict[str, Any]:
        """JSON-able counts and the worst nodes (the node keys of `Extrapolation.to_dict`)."""
        flags = self.flags
        n = flags.shape[1]
        worst = []
        for flat in self.worst().tolist():
            k, i = divmod(flat, n)
            far = None if self.how_far is None else float(self.how_far[k, i])
            component = -1 if self.component is None else int(self.component[k, i])
            worst.append({"trajectory": int(self.trajectory[k]), "node": i,
                          "graph": int(self.graph_index[k]),
                          "in_degree": int(self.in_degree[k, i]),
                          "in_degree_outside": bool(self.degree_outside[k, i]),
                          "how_far": far,
                          "state": self.state_names[component] if component >= 0 else None})
        return {"node_states": self.compared, "trajectory_nodes": int(flags.size),
                "trajectory_nodes_outside": int(np.count_nonzero(flags)),
                "nodes_outside": int(np.count_nonzero(flags.any(axis=0))),
                "state_outside": int(np.count_nonzero(self.state_outside)),
                "in_degree_outside": int(np.count_nonzero(self.degree_outside)),
                "worst": worst}


def node_extrapolation(train: TrainRange, degree: np.ndarray, graph_index: np.ndarray,
                       states: Iterable[torch.Tensor] | None = None, *,
                       compared: str = "true", trajectory: np.ndarray | None = None,
                       state_names: Sequence[str] = ()) -> NodeExtrapolation:
    """Compare every node of every trajectory with a training range: the one computation
    behind `evaluate`, `zeroshot` and `simulate` (`extrapolation`).

    Args:
        train: the training range.
        degree: int `[G, N]` each graph's in-degrees (`Graphs.in_degree`).
        graph_index: `[K]` the graph of each trajectory.
        states: the K trajectories' states in order, physical units, as `[B, T, N, D]`
            blocks (read once); None to compare the in-degrees alone.
        compared: what `states` are, "true" or "predicted" (the report says so).
        trajectory: `[K]` the trajectories' indices for the report (default 0 … K − 1).
        state_names: `[D]` the components' names (default x0, x1, …).

    Raises:
        ValueError: states with another number of components or trajectories.
    """
    graph_index = np.asarray(graph_index, dtype=np.int64).reshape(-1)
    in_degree = np.asarray(degree, dtype=np.int64)[graph_index]  # (K, N)
    how_far = component = fraction = None
    if states is not None:
        how_far, component, fraction = _scan(states, train.states, in_degree.shape[1])
        if how_far.shape != in_degree.shape:
            raise ValueError(f"states of {how_far.shape[0]} trajectories of "
                             f"{how_far.shape[1]} nodes for {len(graph_index)} graph "
                             f"indices of {in_degree.shape[1]} nodes")
        if compared == "predicted":
            component[how_far <= PREDICTED_SLACK] = -1
            how_far[how_far <= PREDICTED_SLACK] = 0.0
    k = len(graph_index)
    return NodeExtrapolation(
        in_degree=in_degree, graph_index=graph_index,
        trajectory=np.arange(k) if trajectory is None else np.asarray(trajectory).reshape(k),
        train_in_degree=train.in_degree, how_far=how_far, component=component,
        compared=None if states is None else compared, outside_fraction=fraction,
        state_names=tuple(state_names) or tuple(f"x{d}" for d in range(len(train.states))))


def _scan(blocks: Iterable[torch.Tensor], ranges: tuple[tuple[float, float], ...],
          n: int) -> tuple[np.ndarray, np.ndarray, float]:
    """`[B, T, N, D]` blocks against per-component `[lo, hi]` ranges, a few trajectories at
    a time: float64 `[K, N]` how far each node goes outside (in range widths), int64
    `[K, N]` the component that does (−1: none), and the fraction of values outside."""
    bounds = torch.tensor(ranges, dtype=torch.float64)  # (D, 2)
    lo, hi = bounds[:, 0], bounds[:, 1]
    width = torch.where(hi > lo, hi - lo, torch.ones_like(lo))
    far, which = [torch.zeros(0, n, dtype=torch.float64)], [torch.zeros(0, n, dtype=torch.long)]
    outside = total = 0
    for block in blocks:
        if block.shape[-1] != len(bounds):
            raise ValueError(f"states have {block.shape[-1]} components, the training range "
                             f"{len(bounds)}")
        rows = max(1, _BLOCK_VALUES // max(int(np.prod(block.shape[1:])), 1))
        for x in torch.as_tensor(block).split(rows):
            x = x.double()
            beyond = torch.maximum(lo - x, x - hi).clamp_(min=0).div_(width)  # (B, T, N, D)
            outside += int(torch.count_nonzero(beyond > 0))
            total += beyond.numel()
            best, component = beyond.amax(dim=1).max(dim=-1)  # (B, N)
            far.append(best)
            which.append(torch.where(best > 0, component, -1))
    fraction = outside / total if total else 0.0
    return torch.cat(far).numpy(), torch.cat(which).numpy(), fraction
