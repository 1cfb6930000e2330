"""Whether a trained model is asked about graphs or states unlike those it was trained on.

A node model learns its dynamics from the in-degrees and states its train split holds. On a
node with many more neighbours than any it saw (a sum over neighbours grows with the
in-degree; PNA's scalers see d beyond the range δ was fitted on) or from states beyond the
train range, its prediction is an extrapolation, which may or may not hold.

Training records the range of its train split (`training_range`, stored in a checkpoint as
`dataset["train_range"]`); `evaluate`, `zeroshot` and `simulate` compare their target with
it (`extrapolation`) and say so when it lies outside. A checkpoint without the record
(written before it existed) is never compared.

The same comparison is made node by node (`NodeExtrapolation`): which nodes of which
trajectories have states (true states for evaluate and zeroshot, predicted ones for
simulate) or in-degrees outside the range, and how far, so that a user can tell which
predictions to trust; `simulate` stores it as the per-node flags `extrapolation [K, N]`
(`STATE_OUTSIDE`, `IN_DEGREE_OUTSIDE`) in its output file.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch

from mpnode_cli.data.dataset import TrajectoryData
from mpnode_cli.data.stream import StreamedTrajectories, in_blocks
from mpnode_cli.graphs import Graphs

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


@dataclass(frozen=True)
class TrainRange:
    """What a model's train split spans.

    Attributes:
        in_degree: `(lo, hi)` in-degree over every node of every train graph.
        num_nodes: `(lo, hi)` node count N of the train graphs.
        states: `((lo, hi),) * D` each state component's range, physical units.
    """

    in_degree: tuple[int, int]
    num_nodes: tuple[int, int]
    states: tuple[tuple[float, float], ...]

    def to_dict(self) -> dict[str, Any]:
        """JSON-able lists, as checkpoints store it."""
        return {"in_degree": list(self.in_degree), "num_nodes": list(self.num_nodes),
                "states": [list(r) for r in self.states]}

    @staticmethod
    def from_dict(d: Any) -> TrainRange:
        """`to_dict`'s inverse.

        Raises:
            ValueError: not such a record.
        """
        try:
            (d_lo, d_hi), (n_lo, n_hi) = d["in_degree"], d["num_nodes"]
            states = tuple((float(lo), float(hi)) for lo, hi in d["states"])
            return TrainRange((int(d_lo), int(d_hi)), (int(n_lo), int(n_hi)), states)
        except (KeyError, TypeError, ValueError) as exc:
            raise ValueError(f"train_range must hold in_degree, num_nodes and per-state "
                             f"[lo, hi] ranges ({exc})") from None


def training_range(*parts: TrajectoryData | StreamedTrajectories) -> TrainRange:
    """The range of the trajectories a model trains on (one train split, or several).

    Streamed data are read once, a block at a time.

    Raises:
        ValueError: no trajectories.
    """
    degrees: list[np.ndarray] = []
    n_lo, n_hi, lo, hi = math.inf, -math.inf, None, None
    for part in parts:
        if len(part) == 0:
            continue
        per_graph = part.graphs.in_degree()  # (G, N)
        used: set[int] = set()
        for block in in_blocks(part):
            used.update(block.graph_index.unique().tolist())
            flat = block.states.reshape(-1, block.states.shape[-1])  # (B·T·N, D)
            b_lo, b_hi = flat.amin(dim=0).double(), flat.amax(dim=0).double()
            lo = b_lo if lo is None else torch.minimum(lo, b_lo)
            hi = b_hi if hi is None else torch.maximum(hi, b_hi)
        degrees.append(per_graph[sorted(used)])
        n_lo, n_hi = min(n_lo, part.num_nodes), max(n_hi, part.num_nodes)
    if lo is None or hi is None:
        raise ValueError("no trajectories to take the training range of")
    d = np.concatenate([g.reshape(-1) for g in degrees])
    return TrainRange((int(d.min()), int(d.max())), (int(n_lo), int(n_hi)),
                      tuple(zip(lo.tolist(), hi.tolist(), strict=True)))


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


def node_lines(record: dict[str, Any] | None) -> list[str]:
    """What a user is told of the nodes outside the training range, from
    `Extrapolation.to_dict`: nothing when every node lies inside, else one line of counts
    and one per worst node (`WORST` at most)."""
    if not record or not record.get("trajectory_nodes_outside"):
        return []
    why = []
    if record["state_outside"]:
        why.append(f"{record['state_outside']} by their {record['node_states']} states")
    if record["in_degree_outside"]:
        why.append(f"{record['in_degree_outside']} by their in-degree")
    lines = [f"{record['nodes_outside']} of {record['num_nodes'][0]} nodes outside the "
             f"training range, in {record['trajectory_nodes_outside']} of "
             f"{record['trajectory_nodes']} trajectory·nodes ({', '.join(why)}); the worst:"]
    for node in record["worst"]:
        said = []
        if node["how_far"]:
            said.append(f"{node['state']} {node['how_far']:.3g} range widths outside")
        said.append(f"in-degree {node['in_degree']}" + (
            f" ({_span(record['train_in_degree'])} in training)"
            if node["in_degree_outside"] else ""))
        lines.append(f"  trajectory {node['trajectory']}, node {node['node']}: "
                     f"{', '.join(said)}")
    return lines


@dataclass(frozen=True)
class Extrapolation:
    """A target compared with a model's training range.

    Attributes:
        in_degree, train_in_degree: `[lo, hi]` here and in training.
        num_nodes, train_num_nodes: `[lo, hi]` N here and in training.
        one_size: the model is built for one N (not `transferable`), so N counts too.
        states_outside_fraction: the fraction of the target's state values (every
            trajectory, time, node and component) outside that component's training
            range; None without ground truth (`simulate`).
        nodes: the same node by node (`NodeExtrapolation`), or None.
    """

    in_degree: list[int]
    train_in_degree: list[int]
    num_nodes: list[int]
    train_num_nodes: list[int]
    one_size: bool
    states_outside_fraction: float | None
    nodes: NodeExtrapolation | None = None

    @property
    def outside(self) -> bool:
        """The graphs lie outside the training range: an in-degree beyond it, or another N
        for a model built for one N."""
        return self._degree_outside or self._size_outside

    @property
    def _degree_outside(self) -> bool:
        return _beyond(self.in_degree, self.train_in_degree)

    @property
    def _size_outside(self) -> bool:
        return self.one_size and _beyond(self.num_nodes, self.train_num_nodes)

    @property
    def note(self) -> str | None:
        """The one line a user is told when the graphs lie outside the range, else None.

        States alone do not make a note: a test split holds states beyond the train
        split's extremes as a matter of course (8% of the values of a 3-trajectory gene
        test split against 11 train trajectories), and a warning on every evaluation would
        go unread. Their fraction joins the note of graphs that lie outside, and `to_dict`
        always holds it.
        """
        if not self.outside:
            return None
        parts = []
        if self._degree_outside:
            parts.append(f"in-degree {_span(self.in_degree)} here, "
                         f"{_span(self.train_in_degree)} in training")
        if self._size_outside:
            parts.append(f"{_span(self.num_nodes)} nodes here, "
                         f"{_span(self.train_num_nodes)} in training")
        fraction = self.states_outside_fraction or 0.0
        if fraction > 0:
            percent = 100 * fraction
            shown = f"{percent:.1f}%" if percent >= 0.1 else "under 0.1%"
            parts.append(f"{shown} of the state values outside the training range")
        return f"extrapolating: {'; '.join(parts)}; a finetune on such graphs may be needed"

    def to_dict(self) -> dict[str, Any]:
        """JSON-able, with the note and the node keys (`NodeExtrapolation.to_dict`)."""
        return {"in_degree": self.in_degree, "train_in_degree": self.train_in_degree,
                "num_nodes": self.num_nodes, "train_num_nodes": self.train_num_nodes,
                "outside": self.outside,
                "states_outside_fraction": self.states_outside_fraction, "note": self.note,
                **({} if self.nodes is None else self.nodes.to_dict())}


def stored_range(ckpt) -> TrainRange | None:
    """A checkpoint's training range; None when it has none (older checkpoints) or it is
    not readable (`mpnode check` reports that)."""
    record = ckpt.dataset.get("train_range") if isinstance(ckpt.dataset, dict) else None
    if record is None:
        return None
    try:
        return TrainRange.from_dict(record)
    except ValueError:
        return None


def extrapolation(ckpt, graphs: Graphs, graph_index: np.ndarray,
                  states: Iterable[torch.Tensor] | None = None, *, predicted: bool = False,
                  trajectory: np.ndarray | None = None) -> Extrapolation | None:
    """Compare a target with the range a checkpoint's model was trained on, as a whole
    and node by node (`node_extrapolation`).

    Args:
        ckpt: a `mpnode_cli.training.checkpoint.Checkpoint`.
        graphs: the target's graphs; graph_index: `[K]` the graph of each trajectory
            (only the graphs used count).
        states: the target's states, physical units, as `[B, T, N, D]` blocks in order
            (e.g. each `in_blocks` block's `states`), read once; None to compare the
            graphs alone.
        predicted: `states` are a model's predictions (simulate), not ground truth: they
            are compared node by node, but give no `states_outside_fraction`.
        trajectory: `[K]` the trajectories' indices for the report (default 0 … K − 1).

    Returns:
        The comparison, or None for a checkpoint without a training range.
    """
    from mpnode_cli.models.registry import OPTIONS, model_class

    train = stored_range(ckpt)
    if train is None:
        return None
    used = np.unique(np.asarray(graph_index, dtype=np.int64))
    degree = graphs.in_degree()[used]  # (G', N)
    here = [int(degree.min()), int(degree.max())] if degree.size else [0, 0]
    n = graphs.num_nodes
    transferable = ckpt.model_kind not in OPTIONS or model_class(ckpt.model_kind).transferable
    nodes = node_extrapolation(train, graphs.in_degree(), graph_index, states,
                               compared="predicted" if predicted else "true",
                               trajectory=trajectory,
                               state_names=ckpt.dataset.get("state_names") or ())
    fraction = None if predicted else nodes.outside_fraction
    return Extrapolation(here, list(train.in_degree), [n, n], list(train.num_nodes),
                         not transferable, fraction, nodes)


def data_extrapolation(ckpt, data: TrajectoryData | StreamedTrajectories,
                       trajectory: np.ndarray | None = None) -> Extrapolation | None:
    """`extrapolation` of trajectories with ground truth (evaluate, zeroshot): their graphs
    and true states, in memory or streamed (read once, a block at a time). `trajectory`:
    `[K]` their rows in the file, for the report (default: a streamed split's own rows,
    else 0 … K − 1)."""
    if isinstance(data, StreamedTrajectories):
        graph_index = data.graph_index[data.rows]
        trajectory = data.rows if trajectory is None else trajectory
    else:
        graph_index = data.graph_index.numpy()
    return extrapolation(ckpt, data.graphs, graph_index,
                         (block.states for block in in_blocks(data)), trajectory=trajectory)


def _beyond(here, train) -> bool:
    return here[0] < train[0] or here[1] > train[1]


def _span(r) -> str:
    return f"{r[0]}" if r[0] == r[1] else f"{r[0]}–{r[1]}"
