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

A batch's graphs come as `[B, N, N]` matrices or as an `EdgeBatch` (`mpnode_cli.graphs`;
what training and evaluation pass above `DENSE_GRAPH_MAX_NODES` nodes). From an
`EdgeBatch`, the scatter backend and the degrees (PNA's scalers and δ) use the edges
directly; no `[N, N]` matrix is built unless the dense backend is chosen for a graph small
enough to hold one.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import ClassVar, get_args

import torch

from mpnode_cli.graphs import DENSE_GRAPH_MAX_NODES, EdgeBatch
from mpnode_cli.models.options import Aggregate, Backend

AGGREGATES: tuple[str, ...] = get_args(Aggregate)
BACKENDS: tuple[str, ...] = get_args(Backend)
DENSE_MAX_NODES = 64  # above this, aggregate over an edge list (memory O(E), not O(B·N²))


def channels(how: str, features: int) -> int:
    """Output features of aggregation `how` applied to `features` input features."""
    return 3 * features if how == "pna" else features


Graph = torch.Tensor | EdgeBatch  # `[B, N, N]` matrices, or the same graphs' edges


def in_degree(adjacency: Graph) -> torch.Tensor:
    """`adjacency: [B, N, N]` (nonzero entries counted) or an `EdgeBatch` → in-degree
    `[B, N]` float64."""
    if isinstance(adjacency, EdgeBatch):
        return adjacency.in_degree()
    return adjacency.ne(0).sum(dim=2).to(torch.float64)


def mean_log_degree(adjacency: Graph | Sequence[Graph]) -> float:
    """PNA's δ: the mean of log(d + 1) over every node of every graph in the batch, or in
    a list of batches (several datasets, whose N differ)."""
    if isinstance(adjacency, torch.Tensor | EdgeBatch):
        return float(torch.log1p(in_degree(adjacency)).mean())
    return float(torch.cat([torch.log1p(in_degree(a)).flatten() for a in adjacency]).mean())


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
        """`adjacency: [B, N, N]` (nonzero = edge j → i) or an `EdgeBatch` → the batch's
        edge list (in the same order either way: by trajectory, receiver, sender)."""
        if isinstance(adjacency, EdgeBatch):
            return EdgeIndex.from_edges(adjacency)
        batch, nodes, _ = adjacency.shape
        b, i, j = torch.nonzero(adjacency, as_tuple=True)
        degree = adjacency.ne(0).sum(dim=2).reshape(-1, 1).to(adjacency.dtype)  # [B·N, 1]
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


def pna_scalers(adjacency: Graph, delta: float) -> tuple[torch.Tensor, torch.Tensor]:
    """PNA's amplification and attenuation scalers `[B, N, 1]` for `adjacency: [B, N, N]`
    or an `EdgeBatch`.

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


# ----------------------------------------------------------- how it is computed: backends


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
        matrices = dense(adjacency)
        self.ones = matrices.ne(0).to(matrices.dtype)  # (B, N, N), unweighted

    def sum(self) -> Callable[[torch.Tensor], torch.Tensor]:
        a = self.ones
        return lambda m: torch.bmm(a.to(m.dtype), m)

    def mean(self) -> Callable[[torch.Tensor], torch.Tensor]:
        a = self.ones / self.ones.sum(dim=2, keepdim=True).clamp_min(1.0)  # isolated rows: 0
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


def strategy(adjacency: Graph, backend: str = "auto") -> Strategy:
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


# ---------------------------------------------------------- what is computed: aggregations


class Aggregation:
    """One way of pooling in-neighbours' features (after PyG's
    `torch_geometric.nn.aggr.Aggregation`), computed by any `Strategy`.

    A subclass names itself (`name`, one of `options.Aggregate`), says how many output
    features it makes per input feature, whether it reads PNA's degree statistic δ, and
    binds itself to a strategy: `bind(strategy) → agg(m [B, N, F]) → [B, N, channels(F)]`.
    """

    name: ClassVar[str]
    multiplier: ClassVar[int] = 1
    degree_statistic: ClassVar[bool] = False

    @classmethod
    def channels(cls, features: int) -> int:
        """Output features for `features` input features."""
        return cls.multiplier * features

    @classmethod
    def fitted(cls, delta: float | None) -> Aggregation:
        """This aggregation for graphs whose degree statistic is `delta` (read only by
        those that declare `degree_statistic`)."""
        return cls()

    def bind(self, strategy: Strategy) -> Callable[[torch.Tensor], torch.Tensor]:
        raise NotImplementedError


class Mean(Aggregation):
    """The paper's choice (§3.2, "we use the mean as the aggregator"). A node cannot tell
    how many neighbours it has."""

    name = "mean"

    def bind(self, strategy: Strategy) -> Callable[[torch.Tensor], torch.Tensor]:
        return strategy.mean()


class Sum(Aggregation):
    """The sum over in-neighbours: a node's response grows with its in-degree, as in systems
    whose coupling adds up over neighbours (see `docs/training-recipe.md`)."""

    name = "sum"

    def bind(self, strategy: Strategy) -> Callable[[torch.Tensor], torch.Tensor]:
        return strategy.sum()


class PNA(Aggregation):
    """Principal Neighbourhood Aggregation (Corso et al. 2020, eqs. 4-5) with the mean and
    the three degree scalers: `[mean, mean · S_amp, mean · S_att]`, `S_amp = log(d + 1) / δ`,
    `S_att = δ / log(d + 1)` (PyG's `DegreeScalerAggregation` with the identity,
    amplification and attenuation scalers).

    Args:
        delta: δ, the training graphs' mean of log(d + 1); fitted once and used unchanged
            on any other graph (zero-shot, finetune).

    Raises:
        ValueError: δ missing, not finite or not positive.
    """

    name = "pna"
    multiplier = 3
    degree_statistic = True

    def __init__(self, delta: float | None):
        if delta is None:
            raise ValueError("PNA aggregation needs the degree statistic δ")
        if not math.isfinite(delta) or delta <= 0:
            raise ValueError(f"PNA needs a positive degree statistic δ, got {delta!r} (fit "
                             "it on training graphs with at least one edge)")
        self.delta = delta

    @classmethod
    def fitted(cls, delta: float | None) -> PNA:
        return cls(delta)

    def scalers(self, adjacency: Graph) -> tuple[torch.Tensor, torch.Tensor]:
        """The amplification and attenuation scalers `[B, N, 1]` for `adjacency: [B, N, N]`
        or an `EdgeBatch`. An isolated node (d = 0) gets 0 for both: its mean is zero
        anyway, and δ / log(1) would be infinite."""
        log_d = torch.log1p(in_degree(adjacency)).unsqueeze(-1)  # (B, N, 1)
        amp = log_d / self.delta
        att = torch.where(log_d > 0, self.delta / log_d.clamp_min(1e-12),
                          torch.zeros_like(log_d))
        return amp, att

    def bind(self, strategy: Strategy) -> Callable[[torch.Tensor], torch.Tensor]:
        base = strategy.mean()
        amp, att = self.scalers(strategy.graph)

        def pna(m: torch.Tensor) -> torch.Tensor:
            mean = base(m)  # (B, N, F)
            return torch.cat([mean, mean * amp.to(m.dtype), mean * att.to(m.dtype)], dim=-1)

        return pna


AGGREGATIONS: dict[str, type[Aggregation]] = {kind.name: kind for kind in (Mean, Sum, PNA)}


def aggregation(how: str) -> type[Aggregation]:
    """The aggregation registered as `how`.

    Raises:
        ValueError: an unknown name.
    """
    if how not in AGGREGATIONS:
        raise ValueError(f"unknown aggregation '{how}' (choose from: {', '.join(AGGREGATES)})")
    return AGGREGATIONS[how]


def registry_aggregator(adjacency: Graph, how: str = "mean", backend: str = "auto",
                        delta: float | None = None) -> Callable[[torch.Tensor], torch.Tensor]:
    kind = aggregation(how)
    compute = strategy(adjacency, backend)
    return kind.fitted(delta).bind(compute)


def aggregator(adjacency: Graph, how: str = "mean", backend: str = "auto",
               delta: float | None = None) -> Callable[[torch.Tensor], torch.Tensor]:
    """The aggregation over one batch of graphs, with its graph work done once.

    Args:
        adjacency: `[B, N, N]` float, `A[b, i, j] ≠ 0` iff j sends to i, or an `EdgeBatch`
            (the dense backend then expands it, for graphs of at most
            `DENSE_GRAPH_MAX_NODES` nodes).
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
    nodes = adjacency.num_nodes if isinstance(adjacency, EdgeBatch) else adjacency.shape[1]
    if backend == "dense" or (backend == "auto" and nodes <= DENSE_MAX_NODES):
        matrices = dense(adjacency)
        a = matrices.ne(0).to(matrices.dtype)
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


def full_graph(adjacency: Graph) -> torch.Tensor:
    """The complete graph with self-loops on the batch's nodes, `[B, N, N]` ones.

    Raises:
        ValueError: more than `DENSE_GRAPH_MAX_NODES` nodes (N² messages per graph).
    """
    if isinstance(adjacency, EdgeBatch):
        n = adjacency.num_nodes
        if n > DENSE_GRAPH_MAX_NODES:
            raise ValueError(f"graph 'full' passes N² messages, too many for {n} nodes (at "
                             f"most {DENSE_GRAPH_MAX_NODES}): use graph 'sys'")
        return torch.ones(adjacency.batch, n, n, device=adjacency.device)
    return torch.ones_like(adjacency)


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

    def _graph(self, adjacency: Graph) -> Graph:
        """The graph messages pass over: the data's, or complete with self-loops."""
        return full_graph(adjacency) if self.graph == "full" else adjacency

    def fit_statistics(self, states: torch.Tensor | None, dt: float,
                       adjacency: Graph | Sequence[Graph]) -> None:
        """Fit PNA's δ on the training graphs `adjacency: [K, N, N]` or an `EdgeBatch`, or
        a list of them (several datasets: pooled over their nodes); states, dt unused."""
        if float(self.degree_delta) == 0.0:  # fitted once: a finetune keeps the parent's
            graphs = (self._graph(adjacency) if isinstance(adjacency, torch.Tensor | EdgeBatch)
                      else [self._graph(a) for a in adjacency])
            self.degree_delta.fill_(mean_log_degree(graphs))

    def aggregator(self, adjacency: Graph, backend: str = "auto"):
        """The aggregation over in-neighbours: `m [B, N, F] → [B, N, channels(F)]`.

        Args:
            adjacency: `[B, N, N]`, `A[b, i, j] ≠ 0` iff j sends to i, or an `EdgeBatch`.
        """
        delta = float(self.degree_delta) if self.aggregate == "pna" else None
        return aggregator(self._graph(adjacency), self.aggregate, backend, delta)
