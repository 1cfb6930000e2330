"""The neighbour sum Σ_j A_ij x_j that most systems' right-hand sides couple through, on
graphs given as matrices or as an `EdgeBatch`; `mpnode_cli.systems.NeighbourSum`.

torch is imported inside the methods, so that importing the registry stays cheap.
"""

from __future__ import annotations

import itertools
from typing import TYPE_CHECKING

from mpnode_cli.graphs.matrices import EdgeBatch

if TYPE_CHECKING:
    import torch


class NeighbourSum:
    """x ↦ Σ_j A_ij x_j for K trajectories, planned once per right-hand side.

    A right-hand side is evaluated hundreds of times per solve, so the plan is made when it
    is built: consecutive trajectories on the same graph (a run) share one GEMM,
    `(k·D, N) @ (N, N)` over their states. The generator keeps each graph's trajectories in
    one block, so a chunk over G graphs costs G small GEMMs per evaluation (one batched
    call when the runs are equally long, the usual case), where a batched matmul over
    per-trajectory copies of A reads all K·N² entries each time (~1.3 ms for 200
    trajectories on 64 nodes, most of a gene solve). When runs are short (distinct graphs
    in most trajectories) that batched matmul is kept, as it is then one call, not many.

    Given an `EdgeBatch` instead (graphs above `DENSE_GRAPH_MAX_NODES` nodes), the sum is
    a scatter over the messages, `out[i] += x[j]` for each j → i (`index_add_`), in O(K·E)
    time and memory instead of O(K·N²): over the shared graph's edges for every
    trajectory at once when the batch is 1, else over the batch's K·N flattened nodes.

    The result equals `adjacency @ x` up to rounding (summation order).
    """

    def __init__(self, adjacency: torch.Tensor | EdgeBatch) -> None:
        """Plan the product.

        Args:
            adjacency: `[K, N, N]` per trajectory, or `[1, N, N]` shared by all (also any
                `[K, M, M]` matrices acting on `[K, M, D]`, e.g. Lorenz's coupling H); or
                an `EdgeBatch` of batch K or 1.
        """
        import torch

        self.edges: tuple[torch.Tensor, torch.Tensor] | None = None  # (senders, receivers)
        self.shared = False
        if isinstance(adjacency, EdgeBatch):
            self.shared = adjacency.batch == 1
            self.edges = adjacency.flat()
            return
        k = adjacency.shape[0]
        new = torch.ones(k, dtype=torch.bool, device=adjacency.device)  # [K] a run starts
        new[1:] = (adjacency[1:] != adjacency[:-1]).flatten(1).any(1)
        starts = [*torch.nonzero(new).flatten().tolist(), k]
        lengths = {b - a for a, b in itertools.pairwise(starts)}
        self.adjacency = adjacency
        # Aᵀ of each run, stacked `[G, N, N]`, when the runs are equally long (or shared).
        self.stacked: torch.Tensor | None = None
        # Otherwise (first trajectory, one past the last, Aᵀ) per run; both None: the
        # per-trajectory batched matmul.
        self.runs: list[tuple[int, int, torch.Tensor]] | None = None
        if len(lengths) == 1:
            self.stacked = adjacency[starts[:-1]].transpose(1, 2).contiguous()
        elif len(starts) - 1 <= k // 2:
            self.runs = [(a, b, adjacency[a].T) for a, b in itertools.pairwise(starts)]

    def __call__(self, x: torch.Tensor) -> torch.Tensor:
        """`x: [K, N, D]` → `[K, N, D]`."""
        import torch

        k, n, d = x.shape
        if self.edges is not None:
            senders, receivers = self.edges
            if self.shared:  # one graph: scatter along the node axis of every trajectory
                return torch.zeros_like(x).index_add_(1, receivers, x[:, senders])
            flat = x.reshape(k * n, d)  # (K·N, D)
            return torch.zeros_like(flat).index_add_(0, receivers, flat[senders]).view_as(x)
        xt = x.transpose(1, 2)  # (K, D, N)
        # Products over explicit (rows, N) blocks: `xt @ Aᵀ` on this transposed view is not
        # folded into one GEMM but run as a batched matmul over a stride-0 Aᵀ, 2-3× slower
        # for D = 1 and ~3× for D = 3 on CPU.
        if self.stacked is not None:  # G runs of K/G trajectories (G = 1 if shared)
            g = self.stacked.shape[0]
            out = torch.bmm(xt.reshape(g, k // g * d, n), self.stacked)  # (G, K/G·D, N)
        elif self.runs is not None:  # one mm per run, stacked back to (K·D, N)
            out = torch.cat([torch.mm(xt[a:b].reshape((b - a) * d, n), a_t)
                             for a, b, a_t in self.runs])  # fmt: skip
        else:
            return self.adjacency @ x
        return out.view(k, d, n).transpose(1, 2)
