"""Neighbour aggregation: mean, sum or PNA, computed densely or over an edge list.

Connectivity convention (jraph's `senders`/`receivers`, PyG's `x_j → x_i`): `A[b, i, j] ≠ 0`
iff node j sends to node i, so node i aggregates over row i. The graph is taken as
unweighted (any nonzero entry is one edge). An isolated node receives zeros (the authors'
`SegmentedMean` returns its zero default for an empty bag: MPNODE.jl, src/empde.jl:53-67).

Three choices of *what* is computed (`how`):
- `mean`: the paper's choice (§3.2, "we use the mean as the aggregator"). A node cannot tell
  how many neighbours it has.
- `sum`: the sum over in-neighbours. Systems whose coupling adds up over neighbours (gene
  regulation, Kuramoto, the pendulum's spring forces) are sums, so a node's response grows
  with its in-degree; the mean hides that (see `docs/training-recipe.md`).
- `pna`: Principal Neighbourhood Aggregation (Corso et al. 2020, "Principal Neighbourhood
  Aggregation for Graph Nets", eqs. 4-5) with the mean aggregator and the three degree
  scalers: `[mean, mean · S_amp, mean · S_att]` with `S_amp = log(d + 1) / δ` and
  `S_att = δ / log(d + 1)`, d the in-degree and δ the training graphs' mean of log(d + 1).
  The output has three times the features. δ is a fitted statistic of the training data,
  kept with the model and used unchanged on any other graph (zero-shot, finetune).

Two implementations of each, tested equal (`backend`):
- dense: a batched `[B, N, N] @ [B, N, F]` product; best for the small, dense graphs of the
  paper (N ≤ 64), where it is one kernel;
- scatter: `index_add_` over the edges of the whole batch flattened to `B·N` nodes; memory
  O(E) rather than O(B·N²), for large sparse graphs. `auto` picks dense up to
  `DENSE_MAX_NODES` nodes.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import get_args

import torch

from mpnode_cli.models.options import Aggregate, Backend

AGGREGATES: tuple[str, ...] = get_args(Aggregate)
BACKENDS: tuple[str, ...] = get_args(Backend)
DENSE_MAX_NODES = 64  # above this, aggregate over an edge list (memory O(E), not O(B·N²))


def channels(how: str, features: int) -> int:
    """Output features of aggregation `how` applied to `features` input features."""
    return 3 * features if how == "pna" else features


def in_degree(adjacency: torch.Tensor) -> torch.Tensor:
    """`adjacency: [B, N, N]` → in-degree `[B, N]` (float), counting nonzero entries."""
    return adjacency.ne(0).sum(dim=2).to(torch.float64)


def mean_log_degree(adjacency: torch.Tensor) -> float:
    """PNA's δ: the mean of log(d + 1) over every node of every graph in `[B, N, N]`."""
    return float(torch.log1p(in_degree(adjacency)).mean())


@dataclass(frozen=True)
class EdgeIndex:
    """The edges of a batch of graphs over `B·N` flattened nodes.

    Attributes:
        senders: `[E]` int64, flattened index `b·N + j` of each edge's sender.
        receivers: `[E]` int64, flattened index `b·N + i` of each edge's receiver.
        inv_degree: `[B·N, 1]`, 1 / in-degree (0 for isolated nodes).
        batch: B; nodes: N.
    """

    senders: torch.Tensor
    receivers: torch.Tensor
    inv_degree: torch.Tensor
    batch: int
    nodes: int

    @staticmethod
    def from_adjacency(adjacency: torch.Tensor) -> EdgeIndex:
        """`adjacency: [B, N, N]` (nonzero = edge j → i) → the batch's edge list."""
        batch, nodes, _ = adjacency.shape
        b, i, j = torch.nonzero(adjacency, as_tuple=True)
        degree = adjacency.ne(0).sum(dim=2).reshape(-1, 1).to(adjacency.dtype)  # [B·N, 1]
        inv = torch.where(degree > 0, 1.0 / degree.clamp_min(1), torch.zeros_like(degree))
        return EdgeIndex(b * nodes + j, b * nodes + i, inv, batch, nodes)


def scatter_sum(edges: EdgeIndex, m: torch.Tensor) -> torch.Tensor:
    """Sum of neighbours' features over an edge list. `m: [B, N, F]` → `[B, N, F]`."""
    flat = m.reshape(edges.batch * edges.nodes, -1)  # (B·N, F)
    return torch.zeros_like(flat).index_add_(0, edges.receivers, flat[edges.senders]).view_as(m)


def scatter_mean(edges: EdgeIndex, m: torch.Tensor) -> torch.Tensor:
    """Mean of neighbours' features over an edge list. `m: [B, N, F]` → `[B, N, F]`."""
    flat = m.reshape(edges.batch * edges.nodes, -1)  # (B·N, F)
    summed = torch.zeros_like(flat).index_add_(0, edges.receivers, flat[edges.senders])
    return (summed * edges.inv_degree.to(m.dtype)).view_as(m)


def pna_scalers(adjacency: torch.Tensor, delta: float) -> tuple[torch.Tensor, torch.Tensor]:
    """PNA's amplification and attenuation scalers `[B, N, 1]` for `adjacency: [B, N, N]`.

    An isolated node (d = 0) gets 0 for both: its mean is zero anyway, and δ / log(1) would
    be infinite.
    """
    if not math.isfinite(delta) or delta <= 0:
        raise ValueError(f"PNA needs a positive degree statistic δ, got {delta!r} (fit it "
                         "on training graphs with at least one edge)")
    log_d = torch.log1p(in_degree(adjacency)).unsqueeze(-1)  # (B, N, 1)
    amp = log_d / delta
    att = torch.where(log_d > 0, delta / log_d.clamp_min(1e-12), torch.zeros_like(log_d))
    return amp, att


def aggregator(adjacency: torch.Tensor, how: str = "mean", backend: str = "auto",
               delta: float | None = None) -> Callable[[torch.Tensor], torch.Tensor]:
    """The aggregation over one batch of graphs, with its graph work done once.

    Args:
        adjacency: `[B, N, N]` float, `A[b, i, j] ≠ 0` iff j sends to i.
        how: "mean", "sum" or "pna".
        backend: "auto", "dense" or "scatter".
        delta: PNA's δ (required for "pna").

    Returns:
        `agg(m: [B, N, F]) → [B, N, channels(how, F)]`.
    """
    if how not in AGGREGATES:
        raise ValueError(f"unknown aggregation '{how}' (choose from: {', '.join(AGGREGATES)})")
    if backend not in BACKENDS:
        raise ValueError(f"unknown backend '{backend}' (choose from: {', '.join(BACKENDS)})")
    nodes = adjacency.shape[1]
    dense = backend == "dense" or (backend == "auto" and nodes <= DENSE_MAX_NODES)
    if dense:
        a = adjacency.ne(0).to(adjacency.dtype)
        if how != "sum":
            a = a / a.sum(dim=2, keepdim=True).clamp_min(1.0)  # isolated rows stay zero
        base = lambda m: torch.bmm(a.to(m.dtype), m)  # noqa: E731
    else:
        edges = EdgeIndex.from_adjacency(adjacency)
        base = (lambda m: scatter_sum(edges, m)) if how == "sum" else (
            lambda m: scatter_mean(edges, m))
    if how != "pna":
        return base
    if delta is None:
        raise ValueError("PNA aggregation needs the degree statistic δ")
    amp, att = pna_scalers(adjacency, delta)

    def pna(m: torch.Tensor) -> torch.Tensor:
        mean = base(m)  # (B, N, F)
        return torch.cat([mean, mean * amp.to(m.dtype), mean * att.to(m.dtype)], dim=-1)

    return pna


class DegreeAwareAggregation:
    """What MP-NODE and GNN-ODE share about their neighbours: the graph mode, PNA's δ and the
    aggregation over one batch of graphs.

    A subclass (an `nn.Module`) sets `self.graph` ("sys" or "full"), `self.aggregate` and
    calls `_register_degree_statistic()` in its constructor.
    """

    graph: str
    aggregate: str
    degree_delta: torch.Tensor

    def _register_degree_statistic(self) -> None:
        # PNA's δ, the training graphs' mean log(in-degree + 1): fitted once by
        # `fit_statistics`, saved with the weights, used unchanged on any other graph.
        self.register_buffer("degree_delta", torch.zeros((), dtype=torch.float64))

    def _graph(self, adjacency: torch.Tensor) -> torch.Tensor:
        """The graph messages pass over: the data's, or complete with self-loops."""
        return torch.ones_like(adjacency) if self.graph == "full" else adjacency

    def fit_statistics(self, states: torch.Tensor | None, dt: float,
                       adjacency: torch.Tensor) -> None:
        """Fit PNA's δ on the training graphs `adjacency: [K, N, N]` (states, dt unused)."""
        if float(self.degree_delta) == 0.0:  # fitted once: a finetune keeps the parent's
            self.degree_delta.fill_(mean_log_degree(self._graph(adjacency)))

    def aggregator(self, adjacency: torch.Tensor, backend: str = "auto"):
        """The aggregation over in-neighbours: `m [B, N, F] → [B, N, channels(F)]`.

        Args:
            adjacency: `[B, N, N]`, `A[b, i, j] ≠ 0` iff j sends to i.
        """
        delta = float(self.degree_delta) if self.aggregate == "pna" else None
        return aggregator(self._graph(adjacency), self.aggregate, backend, delta)
