"""Michaelis–Menten gene regulation (NDCN, Zang & Wang 2020; MPNODE.jl `gene_evolution.jl`).

One scalar state per node:

    ẋ_i = −b·x_i^f + Σ_j A_ij · x_j^h / (1 + x_j^h),    b = 1, f = 1, h = 2.

The n = side² nodes sit on a side×side grid (node i at row i // side, column i % side), but
the grid is only a layout for plots and hot-spot initial states; the coupling is the random
graph. Graphs as in the authors' code (MPNODE.jl `src/systems/gene_evolution.jl:29-50`;
docs/systems.md): `er` G(n, p = 0.5), `ba` Barabási–Albert with m = n/2, `ws`
Watts–Strogatz with k = n/2, p = 0.5 (n // 2 for odd n).

Initial states: `init="uniform"` draws x_i ~ U(0, 50) (the authors' default sampler);
`init="hotspot"` is their `custom_init_state`: three rectangles with start U(0.1, 0.9) and
extent U(0.1, 0.2) of the grid per axis, each filled with one U(30, 50) value, zero elsewhere
(later rectangles overwrite earlier ones).
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING, ClassVar

import numpy as np

from mpnode_cli.systems.base import RHS, Option, System
from mpnode_cli.systems.neighbour_sum import NeighbourSum

if TYPE_CHECKING:
    import torch

INITS: tuple[str, ...] = ("uniform", "hotspot")


class Gene(System):
    """Gene regulatory dynamics with Hill-type activation on a random graph."""

    name: ClassVar[str] = "gene"
    state_names: ClassVar[tuple[str, ...]] = ("x",)
    topologies: ClassVar[tuple[str, ...]] = ("er", "ba", "ws")
    default_topology: ClassVar[str] = "ba"
    default_nodes: ClassVar[int] = 16
    defaults: ClassVar[dict[str, float]] = {"b": 1.0, "f": 1.0, "h": 2.0}
    options: ClassVar[dict[str, Option]] = {"init": Option(
        "uniform", "Initial states: uniform (U(0, 50) per node) or hotspot (three "
        "rectangles on the grid).", choices=INITS)}
    init: str
    # Coupled only through neighbour sums: runs on edge lists, so on graphs of any size.
    sparse: ClassVar[bool] = True
    # Hot-spot initial states are rectangles on the side×side grid: `--grid` means that.
    grid_layout: ClassVar[bool] = True
    # Regulation sums over in-neighbours: the recipe's affine sum update fits it and carries
    # to larger graphs with higher in-degrees (docs/training-recipe.md).
    # The paper's 200 trajectories over 5 graphs, dt 0.1, 5 s, for every topology and size
    # (the paper states it for BA; the other graphs are treated the same way).
    data_defaults: ClassVar[dict[str, float]] = {"trajectories": 200, "t_end": 5.0,
                                                 "dt": 0.1}
    presets: ClassVar[dict[str, dict[str, object]]] = {
        f"gene-{topology}-{side}x{side}": {"grid": side, "topology": topology, "graphs": 5,
                                           "trajectories": 200, "t_end": 5.0, "dt": 0.1}
        for side in (4, 8) for topology in ("ba", "er", "ws")}

    def graph_kwargs(self, topology: str, n: int) -> dict[str, float]:
        """Mean degree about n/2 per topology ("each cell connected to n/2 other cells")."""
        return {"er": {"p": 0.5}, "ba": {"m": n // 2}, "ws": {"k": n // 2, "p": 0.5}}[topology]

    def sample_initial(self, adjacency: np.ndarray, k: int, rng: np.random.Generator) -> np.ndarray:
        """Uniform or hot-spot initial states; float64 `[k, N, 1]`.

        Raises:
            ValueError: `init="hotspot"` on a node count that is not a perfect square.
        """
        n = adjacency.shape[0]
        if self.init == "uniform":
            return rng.uniform(0.0, 50.0, size=(k, n, 1))
        side = math.isqrt(n)
        if side * side != n:
            raise ValueError(f"hot-spot initial states need a square grid, got {n} nodes")
        return np.stack([_hotspots(side, rng) for _ in range(k)]).reshape(k, n, 1)

    def rhs(self, adjacency: torch.Tensor, params: dict[str, torch.Tensor]) -> RHS:
        """f(t [K], y [K, N, 1]) → [K, N, 1]; `adjacency` `[K, N, N]` or an `EdgeBatch`;
        `params` unused."""
        b, f_exp, h = (self.params[key] for key in ("b", "f", "h"))
        neighbour_sum = NeighbourSum(adjacency)

        def f(t: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
            activation = y**h / (1.0 + y**h)  # [K, N, 1]
            return -b * y**f_exp + neighbour_sum(activation)

        return f


def _hotspots(side: int, rng: np.random.Generator) -> np.ndarray:
    """One hot-spot state on a side×side grid, float64 `[side, side]`.

    The authors' 1-based inclusive range ceil(s·side):ceil(e·side) becomes the 0-based
    slice [ceil(s·side) − 1, ceil(e·side)).
    """
    x0 = np.zeros((side, side))
    for _ in range(3):
        start = rng.uniform(0.1, 0.9, size=2)  # [row, column], fractions of the grid
        end = np.minimum(start + rng.uniform(0.1, 0.2, size=2), 1.0)
        lo = np.ceil(start * side).astype(int) - 1
        hi = np.ceil(end * side).astype(int)
        x0[lo[0] : hi[0], lo[1] : hi[1]] = rng.uniform(30.0, 50.0)
    return x0
