"""A system of your own: FitzHugh–Nagumo neurons coupled through their membrane voltages.

Each node is a FitzHugh–Nagumo neuron (FitzHugh, Biophys. J. 1, 445–466, 1961; Nagumo,
Arimoto & Yoshizawa, Proc. IRE 50, 2061–2070, 1962) with state [v, w], voltage and recovery,
and neighbours pull each other's voltages together (diffusive, "electrical" coupling):

    v̇_i = v_i − v_i³/3 − w_i + I + c · Σ_j A_ij (v_j − v_i)
    ẇ_i = ε · (v_i + a − b · w_i)

with FitzHugh's a = 0.7, b = 0.8, ε = 0.08 and a drive I = 0.5 that makes each neuron
oscillate. docs/custom-systems.md walks through this file:

    mpnode generate fhn --system-file examples/fitzhugh_nagumo.py --nodes 6
    mpnode generate --system-file examples/fitzhugh_nagumo.py --preset fhn-chain8
    mpnode generate --system-file examples/fitzhugh_nagumo.py --topology ba --nodes 20

The coupling is an unnormalised sum, so a node's pull grows with its degree: on
Barabási–Albert graphs (m = 2; the largest in-degree grows with N: 7, 12 and 15 at 10, 20
and 40 nodes for graph seed 0) the hubs are tied far more tightly to their neighbours than
the leaves, which a node model trained on small graphs has to carry over to larger hubs
(docs/own-systems.md).
"""

from __future__ import annotations

from typing import ClassVar

import numpy as np

from mpnode_cli.systems import RHS, NeighbourSum, Option, System


class FitzHughNagumo(System):
    """FitzHugh–Nagumo neurons with diffusive voltage coupling on a graph."""

    # What the system is: its name (the dataset's `system`), a node's states, its graphs.
    name: ClassVar[str] = "fhn"
    state_names: ClassVar[tuple[str, ...]] = ("v", "w")
    topologies: ClassVar[tuple[str, ...]] = ("chain", "complete", "er", "ba")
    default_topology: ClassVar[str] = "chain"
    default_nodes: ClassVar[int] = 4

    # Physical parameters (`-p eps=0.1`), stored as attributes of the dataset's `params`:
    # recovery offset a and damping b, time-scale ratio eps, drive I, coupling strength c.
    defaults: ClassVar[dict[str, float]] = {"a": 0.7, "b": 0.8, "eps": 0.08, "I": 0.5,
                                            "c": 0.1}

    # Options that are not physical parameters (`-p ic_box=1.5`), with their help.
    options: ClassVar[dict[str, Option]] = {
        "ic_box": Option(2.0, "Half-width of the uniform box of initial v and w.",
                         minimum=0.0)}
    ic_box: float

    # What `mpnode generate fhn` makes without other options, and a named dataset.
    data_defaults: ClassVar[dict[str, float]] = {"trajectories": 200, "t_end": 20.0,
                                                 "dt": 0.5}
    presets: ClassVar[dict[str, dict[str, object]]] = {
        "fhn-chain8": {"nodes": 8, "topology": "chain", "trajectories": 200,
                       "t_end": 20.0, "dt": 0.5}}

    # How to learn it: the coupling sums over neighbours, which the recipe's default update
    # fits, so it recommends nothing of its own (docs/training-recipe.md).

    def graph_kwargs(self, topology: str, n: int) -> dict[str, float]:
        """G(n, p = 0.5) for `er`; Barabási–Albert with m = 2 edges per new node for `ba`
        (a scale-free graph whose hubs' degree grows with N, mean degree ≈ 4); the chain and
        the complete graph take nothing."""
        if topology == "ba":
            if n <= 2:
                raise ValueError(f"fhn on 'ba' (m=2) needs more than 2 nodes, got {n}")
            return {"m": 2}
        return {"p": 0.5} if topology == "er" else {}

    def sample_initial(self, adjacency: np.ndarray, k: int, rng: np.random.Generator) -> np.ndarray:
        """v and w uniform in [−ic_box, ic_box]; float64 `[k, N, 2]`."""
        return rng.uniform(-self.ic_box, self.ic_box, size=(k, adjacency.shape[0], 2))

    def rhs(self, adjacency, params) -> RHS:
        """f(t [K], y [K, N, 2]) → [K, N, 2]; `adjacency` `[K or 1, N, N]` float64."""
        import torch

        a, b, eps, drive, c = (self.params[key] for key in ("a", "b", "eps", "I", "c"))
        degree = adjacency.sum(dim=-1)  # [K or 1, N]
        neighbour_sum = NeighbourSum(adjacency)

        def f(t: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
            v, w = y[..., 0], y[..., 1]  # [K, N] each
            # Σ_j A_ij (v_j − v_i) = (A v)_i − deg_i · v_i
            pull = neighbour_sum(v.unsqueeze(-1)).squeeze(-1) - degree * v
            dv = v - v**3 / 3 - w + drive + c * pull
            dw = eps * (v + a - b * w)
            return torch.stack((dv, dw), dim=-1)  # [K, N, 2]

        return f
