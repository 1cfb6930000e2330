"""GNN-ODE: the baseline the authors ran under the name "L2S" (`gnnsc_de0`).

MPNODE.jl `exps/models.jl:62-75` and `src/gnnode.jl:39-58, 92-100` (docs/authors-code.md):
a graph network used as a neural-ODE vector field,

    h⁰ = tanh(W_e [x; u] + b_e)
    h  ← tanh(W_b Σ_{j∈N(i)} tanh(W_m h_j + b_m) + b_b) + h      (`depth` times, shared weights)
    ẋ  = W_o (h + h⁰) + b_o

integrated with our Tsit5 over the whole horizon and trained on full rollouts (MSE). Unlike
MP-NODE there are no persistent message states: messages are recomputed from the current
states at every evaluation. Sum aggregation by default, as the authors' (an isolated node
receives zero; their learnable empty-bag default starts at zero and is dropped here);
`aggregate="mean"` or `"pna"` swap in the other choices of `mpnode_cli.models.aggregate`.
"""

from __future__ import annotations

from typing import ClassVar

import torch
from torch import nn

from mpnode_cli.models.aggregate import NeighbourAggregation, build_aggregation, channels
from mpnode_cli.models.backend import Graph
from mpnode_cli.models.ode import Control, NeuralODEModel
from mpnode_cli.models.options import GNODEOptions
from mpnode_cli.models.stacked import Linear
from mpnode_cli.solver.runge_kutta import RHS


class GNODE(NeighbourAggregation, NeuralODEModel):
    """Graph neural ODE with sum aggregation and skip connections.

    Args:
        node_dim: D. control_dim: U. num_nodes: unused (the model runs on any graph).
        options: `GNODEOptions` — hidden, the latent width (32 as shipped); depth,
            message-passing steps per evaluation (1 as shipped; weights shared); graph
            ("sys", the dataset's graph, or "full", complete with self-loops, as shipped);
            aggregate ("sum" as shipped, "mean" or "pna").
    """

    kind: ClassVar[str] = "gnode"
    transferable: ClassVar[bool] = True
    Options: ClassVar[type[GNODEOptions]] = GNODEOptions

    def __init__(self, node_dim: int, control_dim: int = 0, num_nodes: int | None = None,
                 options: GNODEOptions | None = None):
        super().__init__(node_dim, control_dim, num_nodes, options)
        o = self.options
        self.depth, self.graph, hidden = o.depth, o.graph, o.hidden
        self.lift = Linear(node_dim + control_dim, hidden)
        self.message = Linear(hidden, hidden)
        self.update = Linear(channels(o.aggregate, hidden), hidden)
        self.decode = Linear(hidden, node_dim)
        for layer in (self.lift, self.message, self.update, self.decode):
            nn.init.xavier_uniform_(layer.weight)
            nn.init.zeros_(layer.bias)
        self.aggregation = build_aggregation(o.aggregate)

    def vector_field(self, adjacency: Graph, u: Control | None = None) -> RHS:
        """`f(t [B], x [B, N, D]) → ẋ [B, N, D]`, the equations of the module docstring.

        Args:
            adjacency: `[B, N, N]`, or an `EdgeBatch` (large graphs).
            u: `u(t [B]) → [B, N, U]` (zero-order hold), or None when U = 0.
        """
        aggregate = self.aggregator(adjacency)

        def f(t: torch.Tensor, x: torch.Tensor) -> torch.Tensor:
            inputs = torch.cat([x, u(t).to(x.dtype)], dim=-1) if u is not None else x
            h0 = torch.tanh(self.lift(inputs))  # (B, N, H)
            h = h0
            for _ in range(self.depth):
                pooled = aggregate(torch.tanh(self.message(h)))  # (B, N, H')
                h = torch.tanh(self.update(pooled)) + h
            return self.decode(h + h0)

        return f
