"""How an aggregation is computed over a batch of graphs: dense matrices or an edge list.

Connectivity convention (jraph's `senders`/`receivers`, PyG's `x_j → x_i`): `A[b, i, j]`
is the number of edges from node j to node i, so node i aggregates over row i: 0 or 1, or
more in a multigraph (`mpnode generate --hub-multiplicity`), where an edge of
multiplicity w counts as w neighbours, in the sum, the mean and the in-degree. An isolated
node receives zeros (the authors'
`SegmentedMean` returns its zero default for an empty bag: MPNODE.jl, src/empde.jl:53-67).

Two strategies, each giving the sum and the mean over in-neighbours, tested equal
(`backend`; the aggregations of `mpnode_cli.models.aggregate` are built on them):
- dense: a batched `[B, N, N] @ [B, N, F]` product; best for the small, dense graphs of the
  paper (N ≤ 64), where it is one kernel;
- scatter: `index_add_` over the edges of the whole batch flattened to `B·N` nodes; memory
  O(E) rather than O(B·N²), for large sparse graphs. `auto` picks dense up to
  `DENSE_MAX_NODES` nodes.

A batch's graphs come as `[B, N, N]` matrices or as an `EdgeBatch` (`mpnode_cli.graphs.matrices`;
what training and evaluation pass above `DENSE_GRAPH_MAX_NODES` nodes). From an
`EdgeBatch`, the scatter backend uses the edges directly; no `[N, N]` matrix is built
unless the dense backend is chosen for a graph small enough to hold one.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import get_args

import torch

from mpnode_cli.graphs.matrices import DENSE_GRAPH_MAX_NODES, EdgeBatch
from mpnode_cli.models.options import Backend

BACKENDS: tuple[str, ...] = get_args(Backend)
DENSE_MAX_NODES = 64  # above this, aggregate over an edge list (memory O(E), not O(B·N²))

Graph = torch.Tensor | EdgeBatch  # `[B, N, N]` matrices, or the same graphs' edges


def as_graph(adjacency: Graph, x: torch.Tensor) -> Graph:
    """The graphs ready to act on states `x`: matrices in `x`'s dtype and device, edges on
    its device."""
    if isinstance(adjacency, EdgeBatch):
        return adjacency.to(x.device)
    return adjacency.to(device=x.device, dtype=x.dtype)


def dense(adjacency: Graph, dtype: torch.dtype = torch.float32) -> torch.Tensor:
    """The graphs as `[B, N, N]` matrices (an `EdgeBatch` is expanded, which it may only
    be up to `DENSE_GRAPH_MAX_NODES` nodes).

    Raises:
        ValueError: an `EdgeBatch` of more than `DENSE_GRAPH_MAX_NODES` nodes.
    """
    if isinstance(adjacency, EdgeBatch):
        if adjacency.num_nodes > DENSE_GRAPH_MAX_NODES:
            raise ValueError(
                f"dense aggregation needs [N, N] matrices, which mpnode builds for at most "
                f"{DENSE_GRAPH_MAX_NODES} nodes, not {adjacency.num_nodes}: use "
                "backend auto or scatter")
        return adjacency.to_dense(dtype)
    return adjacency


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
    def from_adjacency(adjacency: Graph) -> EdgeIndex:
        """`adjacency: [B, N, N]` (the edges j → i) or an `EdgeBatch` → the batch's edge
        list (in the same order either way: by trajectory, receiver, sender; an edge of
        multiplicity w w times)."""
        if isinstance(adjacency, EdgeBatch):
            return EdgeIndex.from_edges(adjacency)
        batch, nodes, _ = adjacency.shape
        b, i, j = torch.nonzero(adjacency, as_tuple=True)
        counts = adjacency[b, i, j].round().to(torch.int64)
        if counts.numel() and int(counts.max()) > 1:  # a multigraph
            b, i, j = (t.repeat_interleave(counts) for t in (b, i, j))
        degree = adjacency.sum(dim=2).reshape(-1, 1)  # [B·N, 1]
        inv = torch.where(degree > 0, 1.0 / degree.clamp_min(1), torch.zeros_like(degree))
        return EdgeIndex(b * nodes + j, b * nodes + i, inv, batch, nodes)

    @staticmethod
    def from_edges(edges: EdgeBatch) -> EdgeIndex:
        """An `EdgeBatch` → the batch's edge list over `B·N` nodes, degrees from its edges."""
        senders, receivers = edges.flat()
        degree = edges.in_degree().reshape(-1, 1)  # [B·N, 1]
        inv = torch.where(degree > 0, 1.0 / degree.clamp_min(1), torch.zeros_like(degree))
        return EdgeIndex(senders, receivers, inv, edges.batch, edges.num_nodes)


def scatter_sum(edges: EdgeIndex, m: torch.Tensor) -> torch.Tensor:
    """Sum of neighbours' features over an edge list. `m: [B, N, F]` → `[B, N, F]`."""
    flat = m.reshape(edges.batch * edges.nodes, -1)  # (B·N, F)
    return torch.zeros_like(flat).index_add_(0, edges.receivers, flat[edges.senders]).view_as(m)


def scatter_mean(edges: EdgeIndex, m: torch.Tensor) -> torch.Tensor:
    """Mean of neighbours' features over an edge list. `m: [B, N, F]` → `[B, N, F]`."""
    flat = m.reshape(edges.batch * edges.nodes, -1)  # (B·N, F)
    summed = torch.zeros_like(flat).index_add_(0, edges.receivers, flat[edges.senders])
    return (summed * edges.inv_degree.to(m.dtype)).view_as(m)


class Strategy:
    """How an aggregation is computed over one batch of graphs, the graph work done once.

    Attributes:
        graph: the graphs as given, `[B, N, N]` or an `EdgeBatch` (degree scalers read it).
    """

    def __init__(self, adjacency: Graph):
        self.graph = adjacency

    def sum(self) -> Callable[[torch.Tensor], torch.Tensor]:
        """`m [B, N, F] → [B, N, F]`, the sum over each node's in-neighbours."""
        raise NotImplementedError

    def mean(self) -> Callable[[torch.Tensor], torch.Tensor]:
        """`m [B, N, F] → [B, N, F]`, the mean over each node's in-neighbours (zero for none)."""
        raise NotImplementedError


class Dense(Strategy):
    """A batched `[B, N, N] @ [B, N, F]` product: one kernel for small, dense graphs."""

    def __init__(self, adjacency: Graph):
        super().__init__(adjacency)
        self.counts = dense(adjacency)  # (B, N, N), the edges j → i

    def sum(self) -> Callable[[torch.Tensor], torch.Tensor]:
        a = self.counts
        return lambda m: torch.bmm(a.to(m.dtype), m)

    def mean(self) -> Callable[[torch.Tensor], torch.Tensor]:
        a = self.counts / self.counts.sum(dim=2, keepdim=True).clamp_min(1.0)  # isolated: 0
        return lambda m: torch.bmm(a.to(m.dtype), m)


class Scatter(Strategy):
    """`index_add_` over the batch's edges: memory O(E), not O(B·N²), for large graphs."""

    def __init__(self, adjacency: Graph):
        super().__init__(adjacency)
        self.edges = EdgeIndex.from_adjacency(adjacency)

    def sum(self) -> Callable[[torch.Tensor], torch.Tensor]:
        edges = self.edges
        return lambda m: scatter_sum(edges, m)

    def mean(self) -> Callable[[torch.Tensor], torch.Tensor]:
        edges = self.edges
        return lambda m: scatter_mean(edges, m)


STRATEGIES: dict[str, type[Strategy]] = {"dense": Dense, "scatter": Scatter}


def strategy_for(adjacency: Graph, backend: str = "auto") -> Strategy:
    """The backend `backend` ("auto", "dense" or "scatter") over the graphs `adjacency`;
    auto is dense up to `DENSE_MAX_NODES` nodes.

    Raises:
        ValueError: an unknown backend, or dense for an `EdgeBatch` too large to expand.
    """
    if backend not in BACKENDS:
        raise ValueError(f"unknown backend '{backend}' (choose from: {', '.join(BACKENDS)})")
    if backend == "auto":
        nodes = adjacency.num_nodes if isinstance(adjacency, EdgeBatch) else adjacency.shape[1]
        backend = "dense" if nodes <= DENSE_MAX_NODES else "scatter"
    return STRATEGIES[backend](adjacency)
