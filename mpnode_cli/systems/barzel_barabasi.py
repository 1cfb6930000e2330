"""The five Barzel–Barabási systems: SIS, MAK, MM, BD and ND on complex networks.

Barzel & Barabási, "Universality in network dynamics", Nature Physics 9, 673–681 (2013),
write a wide class of network dynamics in one form,

    ẋ_i = M0(x_i) + Σ_j A_ij M1(x_i) M2(x_j),

a self term M0, a factor M1 of the receiver's state and a factor M2 of the sender's.
Laber, Eliassi-Rad & Klein, "When do neural ordinary differential equations generalize on
complex networks?", arXiv:2602.08980 (2026), train neural ODEs of this form on five such
systems on S¹ graphs (Serrano, Krioukov & Boguñá 2008); these are the five, one scalar state
x per node, with the notation of Barzel & Barabási 2013 and Hens et al., "Spatiotemporal
signal propagation in complex networks", Nature Physics 15, 403–412 (2019):

- `sis`, epidemic SIS:
      ẋ_i = −B x_i + R Σ_j A_ij (1 − x_i) x_j,            B = 1, R = 0.3;
- `mak`, biochemical (mass-action kinetics):
      ẋ_i = F − B x_i − R Σ_j A_ij x_i x_j,               F = B = R = 1;
- `mm`, regulatory (Michaelis–Menten):
      ẋ_i = −B x_i^a + R Σ_j A_ij x_j^h / (1 + x_j^h),    B = 1, a = 1, h = 2, R = 1;
- `bd`, population (birth–death):
      ẋ_i = −B x_i^b + R Σ_j A_ij x_j^a,                  B = 1, b = 2, a = 1, R = 1;
- `nd`, neuronal (Wilson–Cowan-like):
      ẋ_i = −B x_i + C tanh x_i + R Σ_j A_ij tanh x_j,    B = C = R = 1.

Where the values come from (the copy of Laber et al. we could read lacks their parameter
table): MM's are those of Gao, Barzel & Barabási, Nature 530, 307–312 (2016) for gene
regulation; B = 1 in SIS is the usual time unit (the mean infectious period); the rest are
ours, unit rates where nothing prefers another scale, SIS's R = 0.3 so that R⟨k⟩/B = 3 at
mean degree 10 (endemic, x ≈ 2/3, neither dying out nor saturating), and BD's b = 2 > a = 1
so that the self term bounds the states.

`mm` at its defaults is the `gene` system's equation (`mpnode_cli/systems/gene.py`: b = 1,
f = 1, h = 2, the values of Gao et al. 2016 that NDCN and the MPNODE authors use), with the
exponent named a and a coupling R in front of the sum; `gene` keeps the authors' dense
graphs (mean degree n/2) and U(0, 50) initial states, `mm` the sparse graphs below.

SIS and MAK need the receiver's state in the coupling (M1(x_i) = 1 − x_i, and −x_i): the
neighbour sum runs over the senders' M2(x_j) alone and is multiplied by M1(x_i) after, so
every system is one neighbour sum (`NeighbourSum`) and runs on edge lists (`sparse`).

Initial states, drawn independently per node: SIS U(0, 1) (probabilities of infection);
MAK U(0, 2), around the uncoupled fixed point F/B = 1; MM and BD U(0, 10), below and
around their active states (≈ R⟨k⟩/B on a graph of mean degree ⟨k⟩ = 10); ND U(−1, 1),
symmetric about its fixed point 0. docs/systems.md gives the sources of every value and
what happens to hubs.

Graphs: `s1` (the S¹ model, degree exponent `gamma`, clustering `beta`, mean degree
`mean_degree`), and `er`, `ba`, `ws` of about the same mean degree; the three are scalar
parameters of every system here (`-p mean_degree=20`), so a dataset records them.
"""

from __future__ import annotations

from abc import abstractmethod
from typing import TYPE_CHECKING, ClassVar

import numpy as np

from mpnode_cli.systems.base import RHS, System
from mpnode_cli.systems.neighbour_sum import NeighbourSum

if TYPE_CHECKING:
    import torch

    from mpnode_cli.graphs.matrices import EdgeBatch

# The graph's parameters, shared by the five systems: S¹ degree exponent γ (scale-free,
# heterogeneous hubs for 2 < γ < 3), inverse temperature β > 1 (clustering grows with β),
# and the mean degree ⟨k⟩ that every topology is built to.
GRAPH_DEFAULTS: dict[str, float] = {"gamma": 2.5, "beta": 2.5, "mean_degree": 10.0}
# Watts–Strogatz rewiring probability: in the small-world regime (short paths, the ring's
# clustering kept).
WS_REWIRING = 0.1


class BarzelBarabasi(System):
    """ẋ_i = M0(x_i) + R · M1(x_i) · Σ_j A_ij M2(x_j), one scalar state per node.

    A subclass sets `name`, its parameters (`defaults`, with `GRAPH_DEFAULTS`), the box of
    its initial states (`initial`) and the three functions, as torch expressions of the
    states and the parameters. `receiver` returns None where M1 = 1.
    """

    state_names: ClassVar[tuple[str, ...]] = ("x",)
    topologies: ClassVar[tuple[str, ...]] = ("s1", "er", "ba", "ws")
    default_topology: ClassVar[str] = "s1"
    default_nodes: ClassVar[int] = 64
    # Coupled only through neighbour sums: runs on edge lists, so on graphs of any size.
    sparse: ClassVar[bool] = True
    # 101 samples over 10 time units: the transients (3-10 time units on graphs of mean
    # degree 10 at the defaults) are resolved and have settled by the end; `bd`, faster,
    # has its own.
    data_defaults: ClassVar[dict[str, float]] = {"trajectories": 100, "t_end": 10.0,
                                                 "dt": 0.1}
    # Initial states: x_i ~ U(low, high), independently per node and trajectory.
    initial: ClassVar[tuple[float, float]]

    @abstractmethod
    def self_term(self, x: torch.Tensor, p: dict[str, float]) -> torch.Tensor:
        """M0(x), the node's own dynamics."""

    def receiver(self, x: torch.Tensor, p: dict[str, float]) -> torch.Tensor | None:
        """M1(x_i), the receiver's factor of the coupling; None for M1 = 1."""
        return None

    @abstractmethod
    def sender(self, x: torch.Tensor, p: dict[str, float]) -> torch.Tensor:
        """M2(x_j), what a sender contributes to its neighbours' sums."""

    def graph_kwargs(self, topology: str, n: int) -> dict[str, float]:
        """The graph parameters for a mean degree of about `mean_degree`: S¹ takes γ, β and
        ⟨k⟩ itself; `er` p = ⟨k⟩/(n − 1) (at most the complete graph); `ba` m = round(⟨k⟩/2)
        in [1, n − 1] (mean degree ≈ 2m); `ws` the even ring degree k nearest ⟨k⟩ below n,
        rewired with p = `WS_REWIRING`.

        Raises:
            ValueError: `mean_degree` not above 0.
        """
        mean = self.params["mean_degree"]
        if not mean > 0:
            raise ValueError(f"{self.name} parameter mean_degree must be > 0, got {mean:g}")
        if topology == "s1":
            return {key: self.params[key] for key in GRAPH_DEFAULTS}
        if topology == "er":
            return {"p": min(mean / (n - 1), 1.0) if n > 1 else 0.0}
        if topology == "ba":
            return {"m": int(min(max(round(mean / 2), 1), n - 1))}
        return {"k": int(min(2 * round(mean / 2), (n - 1) // 2 * 2)), "p": WS_REWIRING}

    def sample_initial(self, adjacency: np.ndarray, k: int, rng: np.random.Generator) -> np.ndarray:
        """x_i ~ U(`initial`) per node; float64 `[k, N, 1]`."""
        low, high = self.initial
        return rng.uniform(low, high, size=(k, adjacency.shape[0], 1))

    def rhs(self, adjacency: torch.Tensor | EdgeBatch, params: dict[str, torch.Tensor]) -> RHS:
        """f(t [K], y [K, N, 1]) → [K, N, 1]; `adjacency` `[K, N, N]` or an `EdgeBatch`;
        `params` unused (no per-graph parameters)."""
        p = dict(self.params)
        neighbour_sum = NeighbourSum(adjacency)

        def f(t: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
            coupling = neighbour_sum(self.sender(y, p))  # Σ_j A_ij M2(x_j)
            factor = self.receiver(y, p)
            if factor is not None:
                coupling = factor * coupling
            return self.self_term(y, p) + p["R"] * coupling

        return f


class SIS(BarzelBarabasi):
    """Epidemic SIS: ẋ_i = −B x_i + R Σ_j A_ij (1 − x_i) x_j; x_i ∈ [0, 1] stays there."""

    name: ClassVar[str] = "sis"
    defaults: ClassVar[dict[str, float]] = {"B": 1.0, "R": 0.3, **GRAPH_DEFAULTS}
    initial: ClassVar[tuple[float, float]] = (0.0, 1.0)

    def self_term(self, x: torch.Tensor, p: dict[str, float]) -> torch.Tensor:
        return -p["B"] * x

    def receiver(self, x: torch.Tensor, p: dict[str, float]) -> torch.Tensor:
        return 1.0 - x

    def sender(self, x: torch.Tensor, p: dict[str, float]) -> torch.Tensor:
        return x


class MAK(BarzelBarabasi):
    """Biochemical mass-action kinetics: ẋ_i = F − B x_i − R Σ_j A_ij x_i x_j."""

    name: ClassVar[str] = "mak"
    defaults: ClassVar[dict[str, float]] = {"F": 1.0, "B": 1.0, "R": 1.0, **GRAPH_DEFAULTS}
    initial: ClassVar[tuple[float, float]] = (0.0, 2.0)

    def self_term(self, x: torch.Tensor, p: dict[str, float]) -> torch.Tensor:
        return p["F"] - p["B"] * x

    def receiver(self, x: torch.Tensor, p: dict[str, float]) -> torch.Tensor:
        return -x

    def sender(self, x: torch.Tensor, p: dict[str, float]) -> torch.Tensor:
        return x


class MM(BarzelBarabasi):
    """Regulatory Michaelis–Menten: ẋ_i = −B x_i^a + R Σ_j A_ij x_j^h / (1 + x_j^h)."""

    name: ClassVar[str] = "mm"
    defaults: ClassVar[dict[str, float]] = {"B": 1.0, "a": 1.0, "h": 2.0, "R": 1.0,
                                            **GRAPH_DEFAULTS}
    initial: ClassVar[tuple[float, float]] = (0.0, 10.0)

    def self_term(self, x: torch.Tensor, p: dict[str, float]) -> torch.Tensor:
        return -p["B"] * x ** p["a"]

    def sender(self, x: torch.Tensor, p: dict[str, float]) -> torch.Tensor:
        xh = x ** p["h"]
        return xh / (1.0 + xh)


class BD(BarzelBarabasi):
    """Population birth–death: ẋ_i = −B x_i^b + R Σ_j A_ij x_j^a."""

    name: ClassVar[str] = "bd"
    defaults: ClassVar[dict[str, float]] = {"B": 1.0, "b": 2.0, "a": 1.0, "R": 1.0,
                                            **GRAPH_DEFAULTS}
    initial: ClassVar[tuple[float, float]] = (0.0, 10.0)
    # Faster than the others: near x* ≈ ⟨k⟩ the self term relaxes at 2B·x* ≈ 20, and the
    # states settle within about 0.6 time units; 101 samples over 2.
    data_defaults: ClassVar[dict[str, float]] = {"trajectories": 100, "t_end": 2.0,
                                                 "dt": 0.02}

    def self_term(self, x: torch.Tensor, p: dict[str, float]) -> torch.Tensor:
        return -p["B"] * x ** p["b"]

    def sender(self, x: torch.Tensor, p: dict[str, float]) -> torch.Tensor:
        return x ** p["a"]


class ND(BarzelBarabasi):
    """Neuronal (Wilson–Cowan-like): ẋ_i = −B x_i + C tanh x_i + R Σ_j A_ij tanh x_j."""

    name: ClassVar[str] = "nd"
    defaults: ClassVar[dict[str, float]] = {"B": 1.0, "C": 1.0, "R": 1.0, **GRAPH_DEFAULTS}
    initial: ClassVar[tuple[float, float]] = (-1.0, 1.0)

    def self_term(self, x: torch.Tensor, p: dict[str, float]) -> torch.Tensor:
        return -p["B"] * x + p["C"] * x.tanh()

    def sender(self, x: torch.Tensor, p: dict[str, float]) -> torch.Tensor:
        return x.tanh()
