"""Graphs as adjacency matrices or edge lists, and the graphs of a dataset.

Convention (used by every dataset and model): `A[i, j] = 1` iff node j sends a message to
node i, i.e. row i lists the senders of receiver i. All generated graphs are undirected, so
`A` is symmetric with a zero diagonal. `edges(A)` gives the jraph/PyG form
`(senders, receivers)`: one entry per directed message, an undirected edge once each way.

Up to `DENSE_GRAPH_MAX_NODES` nodes a graph may be held as its `[N, N]` matrix (one kernel
for a neighbour sum on the paper's small graphs); above it, mpnode holds only edge lists,
so that memory grows with the edges E, not with N² (a 10 000-node graph of mean degree 10
is 10⁵ messages, against 10⁸ matrix entries). Three types carry graphs:
- `EdgeList`: one graph, numpy (what a system's `sample` and `graph_params` get above the
  threshold; it has the matrix's `shape`, so code that only reads N takes either);
- `Graphs`: the G graphs of a dataset, numpy, concatenated edge lists with `num_edges [G]`
  (jraph's `n_edge`), and the dense matrices kept only up to the threshold;
- `EdgeBatch`: the graphs of B trajectories for torch (systems' and models' neighbour sums),
  each distinct graph's edges once plus which graph each trajectory runs on.

The random topologies that make these graphs are `mpnode_cli.graphs.topologies`; a user's
graph as a text file is read by `mpnode_cli.graphs.edge_files`.
"""

from __future__ import annotations

import itertools
from collections.abc import Sequence
from dataclasses import dataclass
from functools import cached_property
from typing import TYPE_CHECKING

import numpy as np

from mpnode_cli.limits import DENSE_GRAPH_MAX_NODES

if TYPE_CHECKING:
    import torch

# Trajectory × edge rows one rollout may hold on graphs kept as edge lists: each row carries
# a message per feature and its two node ids through every solver stage, so 2**22 rows are
# some hundreds of MiB. Rollouts are independent, so batching changes no number.
EDGE_ROWS = 2**22
def edges(adjacency: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Edge list of a graph, one entry per directed message.

    Args:
        adjacency: `[N, N]`, `A[i, j]` the number of edges j → i (0 or 1, or more in a
            multigraph: `mpnode generate --hub-multiplicity`).

    Returns:
        `(senders, receivers)`, int64 `[E]` each, sorted by receiver then sender; an
        undirected edge appears once in each direction, and an edge of multiplicity w
        w times.
    """
    adjacency = np.asarray(adjacency)
    receivers, senders = np.nonzero(adjacency)
    counts = adjacency[receivers, senders].astype(np.int64)
    if counts.size and counts.max() > 1:
        senders, receivers = np.repeat(senders, counts), np.repeat(receivers, counts)
    return senders.astype(np.int64), receivers.astype(np.int64)


def _canonical(n: int, senders: np.ndarray, receivers: np.ndarray, repeats: bool = False
               ) -> tuple[np.ndarray, np.ndarray]:
    """Messages sorted by receiver, then sender (the order `edges` gives), duplicates merged
    unless `repeats` (a multigraph's edge of multiplicity w stays w messages)."""
    key = np.asarray(receivers, np.int64) * n + np.asarray(senders, np.int64)
    key = np.sort(key) if repeats else np.unique(key)
    return key % n, key // n


def degree_range(degree: np.ndarray) -> dict[str, int | float]:
    """`{"min", "median", "max"}` of in-degrees `degree` (e.g. `[G, N]` from
    `Graphs.in_degree`), each entry counted once: every node of every graph, whatever number
    of trajectories runs on it. The median is read off the degrees' histogram, which holds
    max + 1 counts, so no sorted copy of the G·N entries is made."""
    counts = np.bincount(np.asarray(degree, np.int64).reshape(-1))  # [max + 1]
    if not counts.sum():
        raise ValueError("no in-degrees: the graphs hold no node")
    below = np.cumsum(counts)  # below[d]: entries with degree ≤ d
    m = int(below[-1])
    middle = np.searchsorted(below, [(m - 1) // 2, m // 2], side="right")  # sorted positions
    return {"min": int(np.flatnonzero(counts)[0]), "median": float(middle.mean()),
            "max": len(counts) - 1}


@dataclass(frozen=True, eq=False)
class EdgeList:
    """One graph on N nodes as its messages `senders[e] → receivers[e]`.

    Attributes:
        num_nodes: N.
        senders, receivers: int64 `[E]`, sorted by receiver then sender (the order
            `edges(A)` gives, so a graph has one edge list); a message repeats only in a
            multigraph, once per edge.
    """

    num_nodes: int
    senders: np.ndarray
    receivers: np.ndarray

    @staticmethod
    def build(n: int, senders: np.ndarray, receivers: np.ndarray,
              repeats: bool = False) -> EdgeList:
        """The graph of the messages `senders[e] → receivers[e]` on `n` nodes, in canonical
        order with duplicates merged, or kept as a multigraph's parallel edges (`repeats`).

        Raises:
            ValueError: a node id outside 0..n−1.
        """
        senders, receivers = np.asarray(senders), np.asarray(receivers)
        if senders.size and (min(senders.min(), receivers.min()) < 0
                             or max(senders.max(), receivers.max()) >= n):
            raise ValueError(f"edge node ids must lie in 0..{n - 1}")
        return EdgeList(n, *_canonical(n, senders, receivers, repeats))

    @staticmethod
    def from_adjacency(adjacency: np.ndarray) -> EdgeList:
        """`[N, N]`, `A[i, j] != 0` iff j sends to i → its edge list."""
        senders, receivers = edges(adjacency)
        return EdgeList(adjacency.shape[0], senders, receivers)

    @property
    def shape(self) -> tuple[int, int]:
        """`(N, N)`: the shape of the matrix this graph stands for (not held)."""
        return (self.num_nodes, self.num_nodes)

    def __len__(self) -> int:
        """E, the number of messages."""
        return len(self.senders)

    def to_dense(self) -> np.ndarray:
        """uint8 `[N, N]`: the adjacency matrix, `A[i, j]` the edges j → i (O(N²): for small
        graphs or on request)."""
        a = np.zeros(self.shape, dtype=np.uint8)
        np.add.at(a, (self.receivers, self.senders), 1)
        return a

    def in_degree(self) -> np.ndarray:
        """int64 `[N]`: each node's number of senders."""
        return np.bincount(self.receivers, minlength=self.num_nodes)

    def symmetric(self) -> bool:
        """Whether every message j → i has its reverse i → j (an undirected graph)."""
        back = _canonical(self.num_nodes, self.receivers, self.senders, repeats=True)
        return (np.array_equal(back[0], self.senders)
                and np.array_equal(back[1], self.receivers))


@dataclass(frozen=True, eq=False)
class Graphs:
    """The G graphs of a dataset, on the same N nodes.

    Attributes:
        num_nodes: N.
        senders, receivers: int64 `[E_total]`, the graphs' edge lists (`EdgeList` order)
            one after another; graph g's are `[offsets[g], offsets[g + 1])`.
        num_edges: int64 `[G]`, messages per graph (jraph's `n_edge`).
        stored: the `[G, N, N]` matrices as given or read (their dtype kept, since the
            data's `fingerprint` hashes them as stored), only when N ≤
            `DENSE_GRAPH_MAX_NODES`; else None.
    """

    num_nodes: int
    senders: np.ndarray
    receivers: np.ndarray
    num_edges: np.ndarray
    stored: np.ndarray | None = None

    @staticmethod
    def from_adjacency(adjacency: np.ndarray) -> Graphs:
        """`[G, N, N]` matrices (`A[g, i, j] != 0` iff j sends to i) → their graphs; the
        matrices are kept when N ≤ `DENSE_GRAPH_MAX_NODES`."""
        adjacency = np.asarray(adjacency)
        n = adjacency.shape[1]
        graphs = Graphs.from_edge_lists(n, [EdgeList.from_adjacency(a) for a in adjacency])
        keep = adjacency if n <= DENSE_GRAPH_MAX_NODES else None
        return Graphs(n, graphs.senders, graphs.receivers, graphs.num_edges, keep)

    @staticmethod
    def from_edge_lists(n: int, lists: Sequence[EdgeList]) -> Graphs:
        """G `EdgeList`s on `n` nodes → their graphs (no matrix is built)."""
        if any(e.num_nodes != n for e in lists):
            raise ValueError(f"every graph must have {n} nodes")
        cat = (lambda name: np.concatenate([getattr(e, name) for e in lists])  # noqa: E731
               if lists else np.zeros(0, np.int64))
        return Graphs(n, cat("senders"), cat("receivers"),
                      np.asarray([len(e) for e in lists], dtype=np.int64))

    @staticmethod
    def from_concatenated(n: int, senders: np.ndarray, receivers: np.ndarray,
                          num_edges: np.ndarray) -> Graphs:
        """Graphs from concatenated edge lists in any order (as a file may hold them),
        each graph's put in canonical order (a multigraph's repeated messages kept).

        Raises:
            ValueError: `num_edges` that do not add up to the edges, or an id outside 0..n−1.
        """
        num_edges = np.asarray(num_edges, dtype=np.int64)
        if (num_edges < 0).any() or num_edges.sum() != len(senders):
            raise ValueError(f"num_edges adds up to {int(num_edges.sum())} but there are "
                             f"{len(senders)} edges")
        bounds = np.concatenate([[0], np.cumsum(num_edges)])
        return Graphs.from_edge_lists(n, [
            EdgeList.build(n, senders[a:b], receivers[a:b], repeats=True)
            for a, b in itertools.pairwise(bounds)])

    def __len__(self) -> int:
        """G."""
        return len(self.num_edges)

    @cached_property
    def offsets(self) -> np.ndarray:
        """int64 `[G + 1]`: where each graph's edges start (and the total at the end)."""
        return np.concatenate([[0], np.cumsum(self.num_edges)]).astype(np.int64)

    def rollout_batch(self, batch_size: int) -> int:
        """`batch_size`, lowered above `DENSE_GRAPH_MAX_NODES` nodes so that a rollout
        batch holds at most `EDGE_ROWS` trajectory × edge rows (at least one trajectory)."""
        if self.dense_ok or len(self.num_edges) == 0:
            return batch_size
        return max(1, min(batch_size, EDGE_ROWS // max(1, int(self.num_edges.max()))))

    @property
    def dense_ok(self) -> bool:
        """Whether these graphs are small enough to be held as `[N, N]` matrices."""
        return self.num_nodes <= DENSE_GRAPH_MAX_NODES

    def edges(self, g: int) -> EdgeList:
        """Graph g's edge list."""
        a, b = self.offsets[g], self.offsets[g + 1]
        return EdgeList(self.num_nodes, self.senders[a:b], self.receivers[a:b])

    def graph(self, g: int) -> np.ndarray | EdgeList:
        """Graph g as a system takes it: its uint8 `[N, N]` matrix when N ≤
        `DENSE_GRAPH_MAX_NODES`, else its `EdgeList`."""
        return self.dense()[g] if self.dense_ok else self.edges(g)

    def dense(self) -> np.ndarray:
        """`[G, N, N]`: the matrices (as stored, else built as uint8).

        Raises:
            ValueError: N > `DENSE_GRAPH_MAX_NODES` (an N×N matrix mpnode never builds).
        """
        if self.stored is not None:
            return self.stored
        if not self.dense_ok:
            raise ValueError(f"graphs of {self.num_nodes} nodes are held as edge lists, not "
                             f"[N, N] matrices (at most {DENSE_GRAPH_MAX_NODES} nodes)")
        return np.stack([self.edges(g).to_dense() for g in range(len(self))]) if len(
            self) else np.zeros((0, self.num_nodes, self.num_nodes), np.uint8)

    def take(self, index: Sequence[int] | np.ndarray) -> Graphs:
        """The graphs at `index`, in that order."""
        index = np.asarray(index, dtype=np.int64)
        lists = [self.edges(int(g)) for g in index]
        taken = Graphs.from_edge_lists(self.num_nodes, lists)
        stored = None if self.stored is None else self.stored[index]
        return Graphs(self.num_nodes, taken.senders, taken.receivers, taken.num_edges, stored)

    @cached_property
    def multigraph(self) -> bool:
        """Whether some graph holds a message more than once (an edge of multiplicity > 1:
        `mpnode generate --hub-multiplicity`)."""
        graph_of_edge = np.repeat(np.arange(len(self)), self.num_edges)
        key = (graph_of_edge * self.num_nodes + self.receivers) * self.num_nodes + self.senders
        return len(np.unique(key)) != len(key)

    def in_degree(self) -> np.ndarray:
        """int64 `[G, N]`: each node's number of senders in each graph (an edge of
        multiplicity w counted w times)."""
        graph_of_edge = np.repeat(np.arange(len(self)), self.num_edges)
        flat = graph_of_edge * self.num_nodes + self.receivers
        return np.bincount(flat, minlength=len(self) * self.num_nodes).reshape(
            len(self), self.num_nodes)

    def fingerprint_arrays(self) -> tuple[np.ndarray, ...]:
        """What the data's fingerprint hashes of the graphs: the matrices as stored when
        N ≤ `DENSE_GRAPH_MAX_NODES` (as format version 1 did), else the edge lists."""
        if self.dense_ok:
            return (self.dense(),)
        return (self.senders, self.receivers, self.num_edges)

    def batch(self, graph_index: np.ndarray | torch.Tensor,
              device: str | torch.device = "cpu") -> EdgeBatch:
        """The graphs of trajectories running on `graph_index` (`[B]`) as an `EdgeBatch`."""
        import torch

        used, local = np.unique(np.asarray(graph_index, dtype=np.int64), return_inverse=True)
        part = self.take(used) if len(used) != len(self) else self
        return EdgeBatch(
            senders=torch.from_numpy(part.senders).to(device),
            receivers=torch.from_numpy(part.receivers).to(device),
            offsets=torch.from_numpy(part.offsets).to(device),
            graph_index=torch.from_numpy(local.reshape(-1).astype(np.int64)).to(device),
            num_nodes=self.num_nodes)


@dataclass(frozen=True, eq=False)
class EdgeBatch:
    """The graphs of B trajectories for torch, without `[B, N, N]` matrices.

    Each distinct graph's edges are held once; `flat()` lays them out over the batch's
    B·N nodes (jraph's batched `senders`/`receivers`), which is what a scatter needs.

    Attributes:
        senders, receivers: int64 `[E_total]`, the distinct graphs' edges one after
            another (node ids 0..N−1 within each graph).
        offsets: int64 `[G + 1]`, where each graph's edges start.
        graph_index: int64 `[B]`, the graph of each trajectory (B = 1: one graph shared by
            every trajectory, as a `[1, N, N]` matrix is).
        num_nodes: N.
    """

    senders: torch.Tensor
    receivers: torch.Tensor
    offsets: torch.Tensor
    graph_index: torch.Tensor
    num_nodes: int

    @staticmethod
    def from_adjacency(adjacency: torch.Tensor) -> EdgeBatch:
        """`[B, N, N]` (nonzero: j sends to i) → one graph per trajectory (for tests and
        small graphs; large graphs never exist as matrices)."""
        graphs = Graphs.from_adjacency(adjacency.detach().cpu().numpy())
        return graphs.batch(np.arange(adjacency.shape[0]), adjacency.device)

    @property
    def batch(self) -> int:
        """B."""
        return self.graph_index.numel()

    @property
    def device(self) -> torch.device:
        return self.senders.device

    def to(self, device: str | torch.device) -> EdgeBatch:
        """The same graphs on `device`."""
        return EdgeBatch(self.senders.to(device), self.receivers.to(device),
                         self.offsets.to(device), self.graph_index.to(device), self.num_nodes)

    def take(self, index: torch.Tensor) -> EdgeBatch:
        """The graphs of the trajectories at `index` (e.g. each repeated r times)."""
        return EdgeBatch(self.senders, self.receivers, self.offsets,
                         self.graph_index[index.to(self.graph_index.device)], self.num_nodes)

    def in_degree(self) -> torch.Tensor:
        """float64 `[B, N]`: each trajectory's nodes' numbers of senders."""
        import torch

        g = self.offsets.numel() - 1
        counts = self.offsets[1:] - self.offsets[:-1]  # [G]
        graph_of_edge = torch.repeat_interleave(torch.arange(g, device=self.device), counts)
        flat = graph_of_edge * self.num_nodes + self.receivers
        per_graph = torch.bincount(flat, minlength=g * self.num_nodes).view(g, self.num_nodes)
        return per_graph[self.graph_index].to(torch.float64)

    def flat(self) -> tuple[torch.Tensor, torch.Tensor]:
        """`(senders, receivers)` int64 `[Σ_b E_b]` over the B·N flattened nodes: trajectory
        b's edges, in its graph's order, with ids shifted by b·N (trajectory by trajectory)."""
        import torch

        counts = (self.offsets[1:] - self.offsets[:-1])[self.graph_index]  # [B]
        owner = torch.repeat_interleave(torch.arange(self.batch, device=self.device), counts)
        first = torch.cumsum(counts, 0) - counts  # [B] where b's edges start in the output
        position = (torch.arange(owner.numel(), device=self.device) - first[owner]
                    + self.offsets[self.graph_index][owner])  # into the distinct graphs' edges
        shift = owner * self.num_nodes
        return self.senders[position] + shift, self.receivers[position] + shift

    def to_dense(self, dtype: torch.dtype | None = None) -> torch.Tensor:
        """`[B, N, N]` matrices (the number of edges j → i: 1, or more in a multigraph).

        Raises:
            ValueError: N > `DENSE_GRAPH_MAX_NODES`.
        """
        import torch

        n = self.num_nodes
        if n > DENSE_GRAPH_MAX_NODES:
            raise ValueError(f"a graph of {n} nodes is held as an edge list, not an [N, N] "
                             f"matrix (at most {DENSE_GRAPH_MAX_NODES} nodes)")
        senders, receivers = self.flat()
        a = torch.zeros(self.batch * n * n, dtype=dtype or torch.float32, device=self.device)
        owner, i = receivers // n, receivers % n
        a.index_put_((owner * n * n + i * n + senders % n,), a.new_ones(len(senders)),
                     accumulate=True)
        return a.view(self.batch, n, n)
