"""Whether a trained model is asked about graphs or states unlike those it was trained on.

A node model learns its dynamics from the in-degrees and states its train split holds. On a
node with many more neighbours than any it saw (a sum over neighbours grows with the
in-degree; PNA's scalers see d beyond the range δ was fitted on) or from states beyond the
train range, its prediction is an extrapolation, which may or may not hold.

Training records the range of its train split (`mpnode_cli.training.train_range`, stored
in a checkpoint as `dataset["train_range"]`); `evaluate`, `zeroshot` and `simulate` compare
their target with it (`extrapolation`) and say so when it lies outside. A checkpoint without
the record (written before it existed) is never compared.

The same comparison is made node by node (`mpnode_cli.training.extrapolation_nodes`): which
nodes of which trajectories have states (true states for evaluate and zeroshot, predicted
ones for simulate) or in-degrees outside the range, and how far, so that a user can tell
which predictions to trust; `simulate` stores it as the per-node flags
`extrapolation [K, N]` (`STATE_OUTSIDE`, `IN_DEGREE_OUTSIDE`) in its output file.
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch

from mpnode_cli.data.dataset import TrajectoryData
from mpnode_cli.data.stream import StreamedTrajectories, in_blocks
from mpnode_cli.graphs.matrices import Graphs
from mpnode_cli.training.extrapolation_nodes import NodeExtrapolation, node_extrapolation
from mpnode_cli.training.train_range import TrainRange


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
