"""MP-NODE: one neural ODE per node, coupled only through message states.

Gupta, Vemprala & Kapoor (2022), §3.2, eqs. (3)–(5). Node i carries the ODE state
`[x_i (D); m_i (M)]`; messages start at zero. One MLP shared by all nodes maps
`[x_i, u_i, m̄_i] → [ẋ_i, ṁ_i]`, where m̄_i aggregates the *current* messages of i's
in-neighbours (zero for an isolated node), re-evaluated at every solver stage, so messages
pass continuously in time. Only states are supervised; messages run free.

The paper aggregates with the mean (§3.2); `aggregate="sum"` or `"pna"` (see
`mpnode_cli.models.aggregate`) let a node sense its in-degree, which systems whose coupling
is a sum over neighbours need (`docs/training-recipe.md`).

`update="affine"` (mpnode's default recipe; a departure from the paper) replaces the MLP of
`[x_i, u_i, m̄_i]` by a node update that is affine in what the neighbours send, the form of
every additively coupled system (dx_i/dt = f(x_i, u_i) + G(x_i)·Σ_j h(x_j)):

    ẋ_i = F_x(x_i, u_i) + G_x(x_i, u_i) · Σ_j ψ(x_j, u_j, m_j)
    ṁ_i = F_m(x_i, u_i) + G_m(x_i, u_i) · mean_j ψ(x_j, u_j, m_j)

with ψ a learned function of the sender's own state and messages. Because the update is
linear in the neighbour sum, what it learns from nodes of degree 1–8 holds at degree 30
(an MLP fed a sum, or PNA's log-degree scalers, leave their training range there); the
messages' own dynamics see the mean, so their feedback gain does not grow with the degree.
`message_init="learned"` starts the message states from a learned function of
`[x_i(t₀), u_i(t₀)]` instead of zero, for coupling that acts from the first instant.
`periodic="embed"` (off in the paper's model; "auto", mpnode's recipe, embeds where the data
declare angles) feeds the networks (sin θ, cos θ) in place of each
state θ the dataset declares periodic (`periodic_dims`, the indices in the model's config):
an unwrapped angle drifts without bound, and the field, 2π-periodic in it, is then learned
on a bounded input. The ODE state keeps θ; training leaves those components unnormalized
(mean 0, std 1: `mpnode_cli.training.setup`), so the model's θ is in radians.

Settled where the paper is vague (MPNODE.jl, exps/models.jl:92-95 and src/empde.jl): input
order `[x, u, m̄]` and the authors' widths (hidden 32, two tanh layers, M = 3); the whole
horizon is integrated from x(t₀) in one adaptive solve (rtol = atol = 1e-4), with dense
output at the sample times.
Departures: `graph="sys"` (default) passes messages over the dataset's own graph, the
paper's idea; `graph="full"` reproduces what the authors' config actually ran (complete
graph with self-loops, so every node sees the global mean). Each trajectory has its own
adaptive step size (the authors' batch shared one).
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any, ClassVar

import torch

from mpnode_cli.models.aggregate import Mean, NeighbourAggregation, build_aggregation, channels
from mpnode_cli.models.backend import Graph
from mpnode_cli.models.base import mlp
from mpnode_cli.models.ode import Control, NeuralODEModel
from mpnode_cli.models.options import MPNODEOptions
from mpnode_cli.solver.runge_kutta import RHS


class MPNODE(NeighbourAggregation, NeuralODEModel):
    """Message-passing neural ODE over a batch of graphs.

    Args:
        node_dim: D, per-node state size.
        control_dim: U, per-node control size (0 if none).
        num_nodes: unused (the model runs on any graph).
        options: `MPNODEOptions` — message_dim M; hidden, layers, activation of the shared
            MLP; graph ("sys" or "full"); messages (False clamps incoming messages to zero,
            the paper's §4.1 ablation); aggregate ("mean", the paper's, "sum" or "pna");
            update ("mlp", the paper's, or "affine"); message_init ("zero", the paper's,
            or "learned"); periodic ("off", "embed", or "auto": embed the
            `periodic_dims` given, none if none);
            backend ("auto", "dense" or "scatter").
        periodic_dims: the state indices that are angles (the dataset's periodic states);
            used only with `periodic="embed"`, which needs at least one.
    """

    kind: ClassVar[str] = "mpnode"
    transferable: ClassVar[bool] = True
    Options: ClassVar[type[MPNODEOptions]] = MPNODEOptions
    constructor_keys: ClassVar[tuple[str, ...]] = (*NeuralODEModel.constructor_keys,
                                                    "periodic_dims")

    def __init__(self, node_dim: int, control_dim: int = 0, num_nodes: int | None = None,
                 options: MPNODEOptions | None = None, periodic_dims: Sequence[int] = ()):
        super().__init__(node_dim, control_dim, num_nodes, options)
        o = self.options
        self.periodic_dims = tuple(sorted({int(i) for i in periodic_dims})
                                   ) if o.periodic != "off" else ()
        if o.periodic == "embed" and not self.periodic_dims:
            raise ValueError("periodic embed needs the periodic states' indices (the dataset "
                             "declares none)")
        if any(not 0 <= i < node_dim for i in self.periodic_dims):
            raise ValueError(f"periodic_dims {list(self.periodic_dims)} outside the "
                             f"{node_dim} states")
        self._angles = list(self.periodic_dims)
        self._plain = [i for i in range(node_dim) if i not in self.periodic_dims]
        self.message_dim, self.graph, self.messages = o.message_dim, o.graph, o.messages
        self.backend = o.backend
        self.update, self.message_init = o.update, o.message_init
        c = channels(o.aggregate, o.message_dim)
        d, m = node_dim, o.message_dim
        e = d + len(self.periodic_dims)  # the networks' state inputs: sin and cos per angle
        if o.update == "affine":
            # One MLP of [x, u] gives the drift F (D+M) and the gains G_x (D × C), G_m (M × M);
            # a second one, ψ, is what a node sends: a function of its own [x, u, m].
            gains = d * c + m * m
            self.net = mlp(e + control_dim, o.hidden, o.layers, d + m + gains, o.activation)
            self.emit = mlp(e + control_dim + m, o.hidden, 1, m, o.activation)
            with torch.no_grad():  # G = 0: training starts from uncoupled nodes
                self.net[-1].weight[d + m:].zero_()
        else:
            self.net = mlp(e + control_dim + c, o.hidden, o.layers, d + m, o.activation)
        if o.message_init == "learned":
            self.init_net = mlp(e + control_dim, o.hidden, 1, m, o.activation)
        self.aggregation = build_aggregation(o.aggregate)

    @property
    def config(self) -> dict[str, Any]:
        """Sizes and options, and `periodic_dims` when the angles are embedded."""
        config = super().config
        return config | {"periodic_dims": list(self.periodic_dims)} if self.periodic_dims \
            else config

    def embed(self, x: torch.Tensor) -> torch.Tensor:
        """The states `x [..., D]` as the networks see them: `[x_plain, sin θ, cos θ]`
        `[..., D + P]` with the P periodic components θ; x itself when there are none."""
        if not self.periodic_dims:
            return x
        angles = x[..., self._angles]
        return torch.cat([x[..., self._plain], torch.sin(angles), torch.cos(angles)], dim=-1)

    def vector_field(self, adjacency: Graph, u: Control | None = None) -> RHS:
        """`f(t [B], z [B, N, D+M]) → dz/dt [B, N, D+M]`, z = [x; m] per node: eqs. (3)–(5)
        (`update="mlp"`) or the affine update of the module docstring.

        Args:
            adjacency: `[B, N, N]`, or an `EdgeBatch` (large graphs).
            u: `u(t [B]) → [B, N, U]` (zero-order hold), or None when U = 0.
        """
        aggregate = self.aggregator(adjacency, self.backend)
        d, m_dim = self.node_dim, self.message_dim
        if self.update == "mlp":
            def f(t: torch.Tensor, z: torch.Tensor) -> torch.Tensor:
                x, m = z[..., :d], z[..., d:]  # (B, N, D), (B, N, M)
                if not self.messages:
                    m = torch.zeros_like(m)
                rest = [u(t).to(z.dtype)] if u is not None else []
                return self.net(torch.cat([self.embed(x), *rest, aggregate(m)], dim=-1))

            return f
        # The affine update drives the messages by their neighbours' *mean*: a sum there
        # would make the messages' own feedback gain grow with the in-degree, and a node
        # with more neighbours than any in training would see an unstable message ODE.
        average = aggregate if isinstance(self.aggregation, Mean) else Mean().over(
            self._graph(adjacency), self.backend)

        def f(t: torch.Tensor, z: torch.Tensor) -> torch.Tensor:
            x, m = z[..., :d], z[..., d:]  # (B, N, D), (B, N, M)
            view = self.embed(x)
            own = torch.cat([view, u(t).to(z.dtype)], dim=-1) if u is not None else view
            if self.messages:
                sent = self.emit(torch.cat([own, m], dim=-1))  # (B, N, M)
            else:
                sent = own.new_zeros(*own.shape[:-1], m_dim)
            return self._affine(self.net(own), aggregate(sent), average(sent))

        return f

    def _affine(self, out: torch.Tensor, m_sum: torch.Tensor, m_mean: torch.Tensor):
        """`[ẋ; ṁ] = F + [G_x · m̄; G_m · mean m]` from the MLP's `out [B, N, D+M+D·C+M²]`,
        `m_sum [B, N, C]` (the chosen aggregation) and `m_mean [B, N, M]`."""
        d, m, c = self.node_dim, self.message_dim, m_sum.shape[-1]
        drift, g_x, g_m = out.split([d + m, d * c, m * m], dim=-1)
        dx = (g_x.unflatten(-1, (d, c)) @ m_sum.unsqueeze(-1)).squeeze(-1)  # (B, N, D)
        dm = (g_m.unflatten(-1, (m, m)) @ m_mean.unsqueeze(-1)).squeeze(-1)  # (B, N, M)
        return drift + torch.cat([dx, dm], dim=-1)

    def initial_messages(self, x0: torch.Tensor, u0: torch.Tensor | None) -> torch.Tensor:
        """m(t₀) `[B, N, M]`: zero (the paper's), or the learned function of `[x0, u0]`."""
        if self.message_init == "zero":
            return x0.new_zeros(*x0.shape[:-1], self.message_dim)
        e0 = self.embed(x0)
        inputs = torch.cat([e0, u0.to(x0.dtype)], dim=-1) if u0 is not None else e0
        return self.init_net(inputs)

    def initial_state(self, x0: torch.Tensor, u0: torch.Tensor | None) -> torch.Tensor:
        """z(t₀) = `[x0, m(t₀)]` `[B, N, D+M]`: the states and `initial_messages`."""
        return torch.cat([x0, self.initial_messages(x0, u0)], dim=-1)
