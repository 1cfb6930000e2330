"""A system of your own: mutualistic species on a graph of plant–pollinator interactions.

The mutualistic dynamics of Gao, Barzel & Barabási ("Universal resilience patterns in
complex networks", Nature 530, 307–312, 2016, eq. 3), a Barzel–Barabási form
ẋ_i = F(x_i) + Σ_j A_ij G(x_i, x_j) with logistic growth, an Allee effect and a saturating
(Holling type II) benefit from each partner:

    ẋ_i = B + x_i (1 − x_i / K)(x_i / C − 1) + Σ_j A_ij x_i x_j / (D + E x_i + H x_j)

with their B = 0.1, C = 1, K = 5, D = 5, E = 0.9 and H = 0.1. A species with many partners
settles far above the carrying capacity K (a hub's benefit grows with its in-degree), so a
node model trained on small graphs meets, on larger ones, hubs whose states it never saw:

    mpnode generate --system-file examples/mutualistic.py --nodes 20 --graphs 5
    mpnode train datasets/mutualistic-n20-ba-s0.h5 --for-graphs larger.h5

No bench of mpnode was tuned on this system: docs/transfer.md uses it as a held-out check
of `mpnode train --for-graphs`.
"""

from __future__ import annotations

from typing import ClassVar

import numpy as np

from mpnode_cli.systems import RHS, Option, System


class Mutualistic(System):
    """Mutualistic species abundances coupled by Holling type II benefits."""

    name: ClassVar[str] = "mutualistic"
    state_names: ClassVar[tuple[str, ...]] = ("x",)
    topologies: ClassVar[tuple[str, ...]] = ("er", "ba")
    default_topology: ClassVar[str] = "ba"
    default_nodes: ClassVar[int] = 20

    defaults: ClassVar[dict[str, float]] = {"B": 0.1, "C": 1.0, "K": 5.0, "D": 5.0,
                                            "E": 0.9, "H": 0.1}
    options: ClassVar[dict[str, Option]] = {
        "ic_max": Option(5.0, "Initial abundances are uniform in [0, ic_max].", minimum=0.0)}
    ic_max: float

    # Abundances settle within a few time units.
    data_defaults: ClassVar[dict[str, float]] = {"trajectories": 60, "t_end": 4.0,
                                                 "dt": 0.2}

    def graph_kwargs(self, topology: str, n: int) -> dict[str, float]:
        """Barabási–Albert with m = 2 edges per new node; G(n, p = 0.2) for `er`."""
        if topology == "ba":
            if n <= 2:
                raise ValueError(f"mutualistic on 'ba' (m=2) needs more than 2 nodes, got {n}")
            return {"m": 2}
        return {"p": 0.2}

    def sample_initial(self, adjacency: np.ndarray, k: int, rng: np.random.Generator) -> np.ndarray:
        """Abundances uniform in [0, ic_max]; float64 `[k, N, 1]`."""
        return rng.uniform(0.0, self.ic_max, size=(k, adjacency.shape[0], 1))

    def rhs(self, adjacency, params) -> RHS:
        """f(t [K], y [K, N, 1]) → [K, N, 1]; `adjacency` `[K or 1, N, N]` float64."""
        import torch

        b, c, k, d, e, h = (self.params[key] for key in ("B", "C", "K", "D", "E", "H"))

        def f(t: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
            x = y[..., 0]  # [K, N]
            # Σ_j A_ij x_i x_j / (D + E x_i + H x_j): the pair term depends on both ends,
            # so it is summed as a [K, N (i), N (j)] array, one row per receiver (A_ij
            # counts parallel edges, as a multigraph's hubs hear them).
            pair = x.unsqueeze(-1) * x.unsqueeze(-2) / (
                d + e * x.unsqueeze(-1) + h * x.unsqueeze(-2))  # [K, N, N]
            benefit = (adjacency * pair).sum(dim=-1)  # [K, N]
            dx = b + x * (1 - x / k) * (x / c - 1) + benefit
            return dx.unsqueeze(-1)  # [K, N, 1]

        return f
