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

from mpnode_cli.models.base import ACTIVATIONS, NeuralModel, Rollout, control_stops, zoh_controls
from mpnode_cli.models.options import NODEOptions
from mpnode_cli.solver import solve
from mpnode_cli.solver.options import SolverOptions


class NODE(NeuralModel):
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
            modules += [nn.Linear(width, o.hidden), nn.LayerNorm(o.hidden),
                        ACTIVATIONS[o.activation]()]
            width = o.hidden
        modules.append(nn.Linear(width, num_nodes * node_dim))
        self.net = nn.Sequential(*modules)

    def vector_field(self, u=None):
        def f(t: torch.Tensor, x: torch.Tensor) -> torch.Tensor:
            parts = [x, u(t).to(x.dtype)] if u is not None else [x]
            flat = torch.cat(parts, dim=-1).reshape(x.shape[0], -1)  # (B, N·(D+U))
            return self.net(flat).view_as(x)

        return f

    def rollout(self, x0: torch.Tensor, ts: torch.Tensor, adjacency: torch.Tensor,
                controls: torch.Tensor | None = None, *, solver: SolverOptions | None = None,
                return_messages: bool = False) -> Rollout:
        """Integrate from x(t₀); `adjacency` is ignored (only its N is checked)."""
        if x0.shape[1] != self.num_nodes or x0.shape[-1] != self.node_dim:
            raise ValueError(f"this monolithic model is built for {self.num_nodes} nodes × "
                             f"{self.node_dim} features, got {x0.shape[1]} × {x0.shape[-1]}")
        ts = ts.to(device=x0.device, dtype=torch.float64)
        u = zoh_controls(controls, ts) if self.control_dim else None
        options = solver.solve_kwargs() if solver is not None else {}
        sol = solve(self.vector_field(u), x0, ts, **options,
                    tstops=control_stops(controls, ts) if u is not None else None)
        return Rollout(states=sol.ys, messages=None, status=sol.status,
                       n_f_evals=int(sol.stats["n_f_evals"].max()))
