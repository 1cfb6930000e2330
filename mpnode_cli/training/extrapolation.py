"""Whether a trained model is asked about graphs or states unlike those it was trained on.

A node model learns its dynamics from the in-degrees and states its train split holds. On a
node with many more neighbours than any it saw (a sum over neighbours grows with the
in-degree; PNA's scalers see d beyond the range δ was fitted on) or from states beyond the
train range, its prediction is an extrapolation, which may or may not hold.

Training records the range of its train split (`training_range`, stored in a checkpoint as
`dataset["train_range"]`); `evaluate`, `zeroshot` and `simulate` compare their target with
it (`extrapolation`) and say so when it lies outside. A checkpoint without the record
(written before it existed) is never compared.
"""

from __future__ import annotations

import math
from collections.abc import Iterable
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch

from mpnode_cli.data.dataset import TrajectoryData
from mpnode_cli.data.stream import StreamedTrajectories, in_blocks
from mpnode_cli.graphs import Graphs


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
    """

    in_degree: list[int]
    train_in_degree: list[int]
    num_nodes: list[int]
    train_num_nodes: list[int]
    one_size: bool
    states_outside_fraction: float | None

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
        """JSON-able, with the note."""
        return {"in_degree": self.in_degree, "train_in_degree": self.train_in_degree,
                "num_nodes": self.num_nodes, "train_num_nodes": self.train_num_nodes,
                "outside": self.outside,
                "states_outside_fraction": self.states_outside_fraction, "note": self.note}


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
                  states: Iterable[torch.Tensor] | None = None) -> Extrapolation | None:
    """Compare a target with the range a checkpoint's model was trained on.

    Args:
        ckpt: a `mpnode_cli.training.checkpoint.Checkpoint`.
        graphs: the target's graphs; graph_index: `[K]` the graph of each trajectory
            (only the graphs used count).
        states: the target's true states, physical units, as `[..., D]` blocks (e.g. each
            `in_blocks` block's `states [B, T, N, D]`); None without ground truth.

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
    fraction = None if states is None else _outside_fraction(states, train.states)
    return Extrapolation(here, list(train.in_degree), [n, n], list(train.num_nodes),
                         not transferable, fraction)


def data_extrapolation(ckpt, data: TrajectoryData | StreamedTrajectories
                       ) -> Extrapolation | None:
    """`extrapolation` of trajectories with ground truth (evaluate, zeroshot): their graphs
    and true states, in memory or streamed (read once, a block at a time)."""
    if isinstance(data, StreamedTrajectories):
        graph_index = data.graph_index[data.rows]
    else:
        graph_index = data.graph_index.numpy()
    return extrapolation(ckpt, data.graphs, graph_index,
                         (block.states for block in in_blocks(data)))


def _outside_fraction(blocks: Iterable[torch.Tensor],
                      ranges: tuple[tuple[float, float], ...]) -> float:
    """The fraction of values in `blocks` (`[..., D]`) outside their component's range."""
    bounds = torch.tensor(ranges, dtype=torch.float64)  # (D, 2)
    outside = total = 0
    for x in blocks:
        x = x.double()
        if x.shape[-1] != len(bounds):
            raise ValueError(f"states have {x.shape[-1]} components, the training range "
                             f"{len(bounds)}")
        outside += int(((x < bounds[:, 0]) | (x > bounds[:, 1])).sum())
        total += x.numel()
    return outside / total if total else 0.0


def _beyond(here, train) -> bool:
    return here[0] < train[0] or here[1] > train[1]


def _span(r) -> str:
    return f"{r[0]}" if r[0] == r[1] else f"{r[0]}–{r[1]}"
