"""Coupled pendulums: the paper's eq. (6), generalised from 2 nodes to a chain.

Each node is a pendulum (mass m, length l) with state [θ, θ̇]; a spring of stiffness k joins
neighbours. As in MPNODE.jl `src/systems/pendulum.jl:43-52` (docs/systems.md), gravity
enters as m·g, which equals the paper's form at m = 1:

    θ̈_i = [m·sin θ_i·(l·θ̇_i² − g) + k·l·Σ_j A_ij (sin θ_j − sin θ_i)] / (m·l·cos θ_i)

With 2 nodes this is exactly the authors' code. The N-node form is chosen so that
y = l·sin θ is a linear oscillator, m·ÿ_i = −(m·g/l)·y_i + k·Σ_j A_ij (y_j − y_i): each spring
neighbour contributes +k·l·sin θ_j and −k·l·sin θ_i, and the tests compare against that
closed form. The θ-form is singular at cos θ = 0 (|y| = l), so `reject` discards
trajectories that get within |cos θ| < 1e-2 of it.

Initial states: θ ∈ U(−π/4, π/4), θ̇ ∈ U(−0.5, 0.5) as in the authors' code
(`ic_range="small"`); `ic_range="paper"` gives the appendix's U(−π/2, π/2) × U(−1, 1).
Measured over 10 s (400 draws each): the small box never comes near the singularity with
2 nodes, but rejects 11 on a 4-chain and 32 on a 10-chain, where spring energy can gather in
one pendulum; the paper box rejects 80 with 2 nodes and nearly all on a 10-chain.
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING, ClassVar

import numpy as np

from mpnode_cli.systems.base import RHS, Option, System
from mpnode_cli.systems.neighbour_sum import NeighbourSum

if TYPE_CHECKING:
    import torch

# Half-widths of the uniform initial box (θ, θ̇) per `ic_range`.
IC_RANGES: dict[str, tuple[float, float]] = {
    "small": (math.pi / 4, 0.5),
    "paper": (math.pi / 2, 1.0),
}
# |cos θ| below this marks a trajectory as (nearly) singular.
COS_MIN = 1e-2


class Pendulum(System):
    """Spring-coupled pendulums on a chain (paper eq. 6; Gupta et al., NeurIPS 2022)."""

    name: ClassVar[str] = "pendulum"
    state_names: ClassVar[tuple[str, ...]] = ("theta", "theta_dot")
    # θ is an angle (the field has it only in sin θ and cos θ); θ̇ is not.
    periodic_states: ClassVar[tuple[str, ...]] = ("theta",)
    topologies: ClassVar[tuple[str, ...]] = ("chain",)
    default_topology: ClassVar[str] = "chain"
    default_nodes: ClassVar[int] = 2
    defaults: ClassVar[dict[str, float]] = {"m": 1.0, "l": 1.5, "k": 2.0, "g": 9.81}
    options: ClassVar[dict[str, Option]] = {"ic_range": Option(
        "small", "Initial-state box: small (the authors' code) or paper (the appendix's).",
        choices=tuple(IC_RANGES))}
    ic_range: str
    # Coupled only through neighbour sums: runs on edge lists, so on graphs of any size.
    sparse: ClassVar[bool] = True
    # The springs' pull sums over neighbours: the recipe's affine sum update fits it and
    # carries from a chain of 3 to chains of 6 and 12 (docs/training-recipe.md).
    # The paper's 500 trajectories, dt 0.1, 10 s (App. A.1).
    data_defaults: ClassVar[dict[str, float]] = {"trajectories": 500, "t_end": 10.0,
                                                 "dt": 0.1}
    presets: ClassVar[dict[str, dict[str, object]]] = {
        "pendulum": {"nodes": 2, "trajectories": 500, "t_end": 10.0, "dt": 0.1}}

    def sample_initial(self, adjacency: np.ndarray, k: int, rng: np.random.Generator) -> np.ndarray:
        """θ and θ̇ uniform in the `ic_range` box; float64 `[k, N, 2]`."""
        n = adjacency.shape[0]
        half_widths = np.asarray(IC_RANGES[self.ic_range])  # [2]
        return rng.uniform(-1.0, 1.0, size=(k, n, 2)) * half_widths

    def rhs(self, adjacency: torch.Tensor, params: dict[str, torch.Tensor]) -> RHS:
        """f(t [K], y [K, N, 2]) → [K, N, 2]; `adjacency` `[K, N, N]` or an `EdgeBatch`;
        `params` unused."""
        import torch

        m, length, k, g = (self.params[key] for key in ("m", "l", "k", "g"))
        degree = (adjacency.sum(dim=-1) if isinstance(adjacency, torch.Tensor)
                  else adjacency.in_degree())  # [K, N] (or [1, N] when shared)
        neighbour_sum = NeighbourSum(adjacency)

        def f(t: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
            theta, theta_dot = y[..., 0], y[..., 1]  # [K, N] each
            sin, cos = torch.sin(theta), torch.cos(theta)
            # Σ_j A_ij (sin θ_j − sin θ_i), the springs' pull on node i.
            pull = neighbour_sum(sin.unsqueeze(-1)).squeeze(-1)  # [K, N]
            spring = pull - degree * sin
            theta_ddot = (m * sin * (length * theta_dot**2 - g) + k * length * spring) / (
                m * length * cos
            )
            return torch.stack((theta_dot, theta_ddot), dim=-1)  # [K, N, 2]

        return f

    def reject(self, states: np.ndarray) -> np.ndarray:
        """Trajectories whose |cos θ| falls below 1e-2 at a sampled time, or that are not finite.

        Only the sampled times are checked. A trajectory that passes closer between samples
        makes θ̇ blow up there, so the solver fails on it and fills its later outputs with NaN,
        which this flags as well.

        Args:
            states: `[K, T, N, 2]`.

        Returns:
            bool `[K]`.
        """
        cos = np.abs(np.cos(states[..., 0]))  # [K, T, N]
        # `not >=` so that NaN (a blown-up trajectory) counts as rejected.
        return ~(cos.reshape(cos.shape[0], -1) >= COS_MIN).all(axis=1)
