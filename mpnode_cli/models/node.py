"""A monolithic neural ODE over the whole system state (the authors' `ndeln4`).

MPNODE.jl `exps/models.jl:25-31` (docs/authors-code.md): `Chain(DenseLN(N·(D+U) → 32, tanh),
DenseLN(32 → 32, tanh), Dense(32 → N·D))` with `DenseLN` = Dense then LayerNorm. It sees
every node at once, so it is tied to one node count N and cannot transfer to another graph
size (`transferable = False`).
The graph is not an input: coupling must be learned from the concatenated state.
"""

from __future__ import annotations

from typing import ClassVar

import torch
from torch import nn

from mpnode_cli.models.backend import Graph
from mpnode_cli.models.base import ACTIVATIONS
from mpnode_cli.models.ode import Control, NeuralODEModel
from mpnode_cli.models.options import NODEOptions
from mpnode_cli.models.stacked import LayerNorm, Linear
from mpnode_cli.solver.runge_kutta import RHS


class NODE(NeuralODEModel):
    """Neural ODE on the flattened state `[N·D]` of the whole system.

    Args:
        node_dim: D. control_dim: U. num_nodes: N (required: the model is built for it).
        options: `NODEOptions` — hidden, layers, activation of the MLP (each hidden layer
            Linear → LayerNorm → activation).
    """

    kind: ClassVar[str] = "node"
    transferable: ClassVar[bool] = False
    Options: ClassVar[type[NODEOptions]] = NODEOptions

    def __init__(self, node_dim: int, control_dim: int = 0, num_nodes: int | None = None,
                 options: NODEOptions | None = None):
        super().__init__(node_dim, control_dim, num_nodes, options)
        o = self.options
        width = num_nodes * (node_dim + control_dim)
        modules: list[nn.Module] = []
        for _ in range(o.layers):
            modules += [Linear(width, o.hidden), LayerNorm(o.hidden),
                        ACTIVATIONS[o.activation]()]
            width = o.hidden
        modules.append(Linear(width, num_nodes * node_dim))
        self.net = nn.Sequential(*modules)

    def vector_field(self, adjacency: Graph, u: Control | None = None) -> RHS:
        """`f(t [B], x [B, N, D]) → ẋ [B, N, D]`: the MLP of the flattened `[x, u]`.

        Args:
            adjacency: ignored (coupling is learned from the concatenated state).
            u: `u(t [B]) → [B, N, U]` (zero-order hold), or None when U = 0.
        """
        def f(t: torch.Tensor, x: torch.Tensor) -> torch.Tensor:
            parts = [x, u(t).to(x.dtype)] if u is not None else [x]
            flat = torch.cat(parts, dim=-1).reshape(x.shape[0], -1)  # (B, N·(D+U))
            return self.net(flat).view_as(x)

        return f
