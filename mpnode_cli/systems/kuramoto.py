"""Kuramoto oscillators with 3 phase components per node (MPNODE.jl `src/systems/kuramoto.jl`).

Each node carries 3 independent phases, coupled component-wise along the graph:

    θ̇_i = ω + K · Σ_j A_ij · sin(θ_j − θ_i),    K = 1/3, no degree normalisation,

with one natural-frequency vector ω ~ N(0, I₃) per graph, shared by all its nodes
(`src/systems/kuramoto.jl:25-54`). Phases are not wrapped. Initial states U(−1, 1).

Graph g's ω is drawn from the graph's generator, `default_rng([graph_seed, g])`, so two
datasets with the same graph seed (the BA and ER presets) share their ω and differ only in
the adjacency. `-p omega_seed=S` (S > 0) draws it from a generator seeded by S and that
one instead: other frequencies, still one per graph. The default (0) leaves every dataset
as it was.

Graphs with mean degree ≈ 5, the paper's "each node connected to 5 other nodes" (App. A.4):
`ba` with m = 5 (needs N > 5), `er` G(n, M) with M = round(5n/2) edges (halves round up;
capped at the complete graph), `ws` with k = 4, p = 0.5. We follow the paper here, not the
authors' code: their ER graph, LightGraphs' `erdos_renyi(10, 5)` (`kuramoto.jl:58`), takes
the integer 5 as an edge count, so it has 5 edges and mostly isolated nodes, a nearly
uncoupled system rather than another topology of the same one (docs/systems.md).
"""

from __future__ import annotations

from typing import TYPE_CHECKING, ClassVar

import numpy as np

from mpnode_cli.systems.base import RHS, Option, System
from mpnode_cli.systems.neighbour_sum import NeighbourSum

if TYPE_CHECKING:
    import torch


class Kuramoto(System):
    """Homogeneous Kuramoto oscillators, 3 phases per node, unnormalised coupling K."""

    name: ClassVar[str] = "kuramoto"
    state_names: ClassVar[tuple[str, ...]] = ("theta1", "theta2", "theta3")
    # Every component is a phase: the field depends on them through sin and cos only.
    periodic_states: ClassVar[tuple[str, ...]] = ("theta1", "theta2", "theta3")
    topologies: ClassVar[tuple[str, ...]] = ("ba", "er", "ws")
    default_topology: ClassVar[str] = "ba"
    default_nodes: ClassVar[int] = 10
    defaults: ClassVar[dict[str, float]] = {"K": 1.0 / 3.0}
    options: ClassVar[dict[str, Option]] = {"omega_seed": Option(
        0, "Seed of the natural frequencies ω: 0 draws them from each graph's seed (BA and "
        "ER of one graph seed share them); a whole number S > 0 draws others.", minimum=0)}
    omega_seed: float
    paper_loss: ClassVar[str] = "huber"  # the paper's App. A.4
    # Coupled only through neighbour sums: runs on edge lists, so on graphs of any size.
    sparse: ClassVar[bool] = True
    # The coupling sums over neighbours: the recipe's affine sum update fits it (Σ_j
    # sin(θ_j − θ_i) is affine in Σ_j sin θ_j and Σ_j cos θ_j; docs/training-recipe.md).
    # The paper gives 500 trajectories at dt 0.05 but no horizon; the authors' 50 steps.
    data_defaults: ClassVar[dict[str, float]] = {"trajectories": 500, "t_end": 2.5,
                                                 "dt": 0.05}
    presets: ClassVar[dict[str, dict[str, object]]] = {
        f"kuramoto10-{topology}": {"nodes": 10, "topology": topology, "trajectories": 500,
                                   "t_end": 2.5, "dt": 0.05}
        for topology in ("ba", "er", "ws")}

    def __init__(self, **given: float | str) -> None:
        super().__init__(**given)
        if not float(self.omega_seed).is_integer():
            raise ValueError(f"kuramoto option omega_seed must be a whole number, got "
                             f"{given.get('omega_seed')!r}")

    def graph_kwargs(self, topology: str, n: int) -> dict[str, float]:
        """Mean degree ≈ 5 for each topology."""
        if topology == "ba":
            if n <= 5:
                raise ValueError(f"kuramoto on 'ba' (m=5) needs more than 5 nodes, got {n}")
            return {"m": 5}
        if topology == "er":
            return {"m_edges": min((5 * n + 1) // 2, n * (n - 1) // 2)}
        return {"k": 4, "p": 0.5}

    def graph_params(
        self, adjacency: np.ndarray, rng: np.random.Generator
    ) -> dict[str, np.ndarray]:
        """`{"omega": float64 [3]}`, the natural frequencies shared by the graph's nodes:
        from `rng` (the graph's), or with `omega_seed` from a generator seeded by it and
        by a draw of `rng` (so the graphs of one dataset still differ)."""
        if self.omega_seed:
            rng = np.random.default_rng([int(self.omega_seed), *rng.integers(2**32, size=2)])
        return {"omega": rng.standard_normal(3)}

    def sample_initial(self, adjacency: np.ndarray, k: int, rng: np.random.Generator) -> np.ndarray:
        """Phases U(−1, 1); float64 `[k, N, 3]`."""
        return rng.uniform(-1.0, 1.0, size=(k, adjacency.shape[0], 3))

    def rhs(self, adjacency: torch.Tensor, params: dict[str, torch.Tensor]) -> RHS:
        """f(t [K], y [K, N, 3]) → [K, N, 3], with `params["omega"]` `[K, 3]`."""
        import torch

        coupling = self.params["K"]
        omega = params["omega"].unsqueeze(1)  # [K, 1, 3], shared by the nodes
        neighbour_sum = NeighbourSum(adjacency)

        def f(t: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
            # Σ_j A_ij sin(θ_j − θ_i) = cos θ_i (A sin θ)_i − sin θ_i (A cos θ)_i: two
            # matmuls instead of a [K, N, N, 3] tensor of pairwise differences.
            sin, cos = torch.sin(y), torch.cos(y)  # [K, N, 3]
            return omega + coupling * (
                cos * neighbour_sum(sin) - sin * neighbour_sum(cos)
            )

        return f
