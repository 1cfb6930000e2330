"""Neighbour aggregation: mean, sum or PNA, each a small `nn.Module` registered by name.

An aggregation (after PyG's `torch_geometric.nn.aggr`) pools the features of each node's
in-neighbours; `how` names it, one of `options.Aggregate`, the one declared list. How it is
computed, densely or over an edge list (`backend`), is a `Strategy` of
`mpnode_cli.models.backend`. From an `EdgeBatch`, the degrees (PNA's scalers and δ) are
read from the edges directly.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from typing import ClassVar, get_args

import torch
from torch import nn

from mpnode_cli.graphs.matrices import DENSE_GRAPH_MAX_NODES, EdgeBatch
from mpnode_cli.models.backend import Graph, Strategy, strategy_for
from mpnode_cli.models.options import Aggregate

AGGREGATES: tuple[str, ...] = get_args(Aggregate)


def in_degree(adjacency: Graph) -> torch.Tensor:
    """`adjacency: [B, N, N]` (the edges j → i, counted with their multiplicity) or an
    `EdgeBatch` → in-degree `[B, N]` float64."""
    if isinstance(adjacency, EdgeBatch):
        return adjacency.in_degree()
    return adjacency.to(torch.float64).sum(dim=2)


def mean_log_degree(adjacency: Graph | Sequence[Graph]) -> float:
    """PNA's δ: the mean of log(d + 1) over every node of every graph in the batch, or in
    a list of batches (several datasets, whose N differ)."""
    if isinstance(adjacency, torch.Tensor | EdgeBatch):
        return float(torch.log1p(in_degree(adjacency)).mean())
    return float(torch.cat([torch.log1p(in_degree(a)).flatten() for a in adjacency]).mean())


class Aggregation(nn.Module):
    """One way of pooling in-neighbours' features, a module as PyG's
    `torch_geometric.nn.aggr.Aggregation` (built once, in the model's constructor, from
    the options' name), computed by any `Strategy`.

    A subclass names itself (`name`, one of `options.Aggregate`), says how many output
    features it makes per input feature and whether it reads the training graphs' degree
    statistic (then `fit` sets it, once), and binds itself to a strategy:
    `bind(strategy) → agg(m [B, N, F]) → [B, N, channels(F)]`.
    """

    name: ClassVar[str]
    multiplier: ClassVar[int] = 1
    degree_statistic: ClassVar[bool] = False

    @classmethod
    def channels(cls, features: int) -> int:
        """Output features for `features` input features."""
        return cls.multiplier * features

    @property
    def fitted(self) -> bool:
        """Whether what it reads of the training graphs is set (nothing to set here)."""
        return True

    def fit(self, graphs: Graph | Sequence[Graph]) -> None:
        """Fit the degree statistic on the training graphs (none here)."""

    def over(self, adjacency: Graph, backend: str = "auto"
             ) -> Callable[[torch.Tensor], torch.Tensor]:
        """The aggregation over one batch of graphs (`aggregator`'s arguments), its graph
        work done once."""
        return self.bind(strategy_for(adjacency, backend))

    def bind(self, strategy: Strategy) -> Callable[[torch.Tensor], torch.Tensor]:
        raise NotImplementedError


class Mean(Aggregation):
    """The paper's choice (§3.2, "we use the mean as the aggregator"). A node cannot tell
    how many neighbours it has."""

    name = "mean"

    def bind(self, strategy: Strategy) -> Callable[[torch.Tensor], torch.Tensor]:
        return strategy.mean()


class Sum(Aggregation):
    """The sum over in-neighbours. Systems whose coupling adds up over neighbours (gene
    regulation, Kuramoto, the pendulum's spring forces) are sums, so a node's response grows
    with its in-degree; the mean hides that (see `docs/training-recipe.md`)."""

    name = "sum"

    def bind(self, strategy: Strategy) -> Callable[[torch.Tensor], torch.Tensor]:
        return strategy.sum()


class PNA(Aggregation):
    """Principal Neighbourhood Aggregation (Corso et al. 2020, "Principal Neighbourhood
    Aggregation for Graph Nets", eqs. 4-5) with the mean aggregator and the three degree
    scalers: `[mean, mean · S_amp, mean · S_att]` with `S_amp = log(d + 1) / δ` and
    `S_att = δ / log(d + 1)`, d the in-degree (PyG's `DegreeScalerAggregation` with the
    identity, amplification and attenuation scalers). The output has three times the
    features.

    Args:
        delta: δ, the training graphs' mean of log(d + 1), or None to fit it later
            (`fit`). A buffer of the module: saved with the weights, and used unchanged
            on any other graph (zero-shot, finetune).
    """

    name = "pna"
    multiplier = 3
    degree_statistic = True
    delta: torch.Tensor

    def __init__(self, delta: float | None = None):
        super().__init__()
        # 0: not yet fitted (the statistic of graphs with an edge is positive).
        self.register_buffer("delta", torch.tensor(0.0 if delta is None else float(delta),
                                                   dtype=torch.float64))

    @property
    def fitted(self) -> bool:
        return float(self.delta) != 0.0

    def fit(self, graphs: Graph | Sequence[Graph]) -> None:
        """δ of the training graphs, once: a finetune keeps its parent's."""
        if not self.fitted:
            self.delta.fill_(mean_log_degree(graphs))

    def scalers(self, adjacency: Graph) -> tuple[torch.Tensor, torch.Tensor]:
        """The amplification and attenuation scalers `[B, N, 1]` for `adjacency: [B, N, N]`
        or an `EdgeBatch`. An isolated node (d = 0) gets 0 for both: its mean is zero
        anyway, and δ / log(1) would be infinite.

        Raises:
            ValueError: δ not finite or not positive (not fitted).
        """
        delta = float(self.delta)
        if not math.isfinite(delta) or delta <= 0:
            raise ValueError(f"PNA needs a positive degree statistic δ, got {delta!r} (fit "
                             "it on training graphs with at least one edge)")
        log_d = torch.log1p(in_degree(adjacency)).unsqueeze(-1)  # (B, N, 1)
        amp = log_d / delta
        att = torch.where(log_d > 0, delta / log_d.clamp_min(1e-12), torch.zeros_like(log_d))
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
    kind = aggregation(how)
    if kind.degree_statistic and delta is None:
        raise ValueError(f"{how} aggregation needs the degree statistic δ")
    return (kind(delta) if kind.degree_statistic else kind()).over(adjacency, backend)


def build_aggregation(how: str) -> Aggregation:
    """The aggregation module registered as `how`, its statistic (if any) not yet fitted.

    Raises:
        ValueError: an unknown name.
    """
    return aggregation(how)()


def channels(how: str, features: int) -> int:
    """Output features of aggregation `how` applied to `features` input features."""
    return aggregation(how).channels(features)


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


class NeighbourAggregation:
    """What MP-NODE and GNN-ODE share about their neighbours: the graph mode and the
    aggregation module.

    A subclass (an `nn.Module`) sets `self.graph` ("sys" or "full") and
    `self.aggregation = build_aggregation(options.aggregate)` in its constructor.
    """

    graph: str
    aggregation: Aggregation

    def _graph(self, adjacency: Graph) -> Graph:
        """The graph messages pass over: the data's, or complete with self-loops."""
        return full_graph(adjacency) if self.graph == "full" else adjacency

    def fit_statistics(self, states: torch.Tensor | None, dt: float,
                       adjacency: Graph | Sequence[Graph]) -> None:
        """Fit the aggregation's degree statistic (PNA's δ) on the training graphs
        `adjacency: [K, N, N]` or an `EdgeBatch`, or a list of them (several datasets:
        pooled over their nodes), once; states, dt unused."""
        if not self.aggregation.fitted:
            self.aggregation.fit(
                self._graph(adjacency) if isinstance(adjacency, torch.Tensor | EdgeBatch)
                else [self._graph(a) for a in adjacency])

    def aggregator(self, adjacency: Graph, backend: str = "auto"):
        """The aggregation over in-neighbours: `m [B, N, F] → [B, N, channels(F)]`.

        Args:
            adjacency: `[B, N, N]`, `A[b, i, j] ≠ 0` iff j sends to i, or an `EdgeBatch`.
        """
        return self.aggregation.over(self._graph(adjacency), backend)
