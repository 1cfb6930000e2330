"""What a model's train split spans: `training_range(...) -> TrainRange`.

Training records it in every checkpoint as `dataset["train_range"]`
(`mpnode_cli.training.setup`); `evaluate`, `zeroshot` and `simulate` compare their target
with it (`mpnode_cli.training.extrapolation`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch

from mpnode_cli.data.dataset import TrajectoryData
from mpnode_cli.data.stream import StreamedTrajectories, in_blocks


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
