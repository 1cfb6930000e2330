"""The interface every dynamical system on a graph implements.

A system is homogeneous: N identical nodes, each with a D-dimensional state
(`state_names`), coupled along a graph. Generating data for it takes five pieces, one
method each: its graph (`graph`), the parameters drawn once per graph (`graph_params`),
initial states (`sample_initial`), a batched torch right-hand side (`rhs`), and an optional
filter of trajectories to redraw (`reject`).

Systems know nothing of files or solvers. torch is imported inside `rhs` implementations so
that importing the registry (for the CLI's choices) stays cheap.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from collections.abc import Callable
from typing import TYPE_CHECKING, ClassVar

import numpy as np

from mpnode_cli.graphs import make_graph

if TYPE_CHECKING:
    import torch

RHS = Callable[["torch.Tensor", "torch.Tensor"], "torch.Tensor"]


class System(ABC):
    """A homogeneous dynamical system on a graph.

    Subclasses set the class attributes below and `defaults` (scalar parameters and their
    default values, written as attributes of the dataset's `params` group). Per-instance
    options that are not physical parameters (e.g. the initial-state range) are keyword-only
    arguments of the subclass's `__init__`, listed in `options` and stored as attributes of
    the same name.
    """

    name: ClassVar[str]
    state_names: ClassVar[tuple[str, ...]]
    control_names: ClassVar[tuple[str, ...]] = ()
    topologies: ClassVar[tuple[str, ...]]
    default_topology: ClassVar[str]
    default_nodes: ClassVar[int]
    defaults: ClassVar[dict[str, float]]
    options: ClassVar[tuple[str, ...]] = ()

    def __init__(self, **params: float) -> None:
        """Set the scalar parameters, each defaulting to `defaults`.

        Raises:
            ValueError: a key that is neither a parameter nor an option of this system.
        """
        unknown = sorted(set(params) - set(self.defaults))
        if unknown:
            known = ", ".join(self.defaults)
            opts = f"; options: {', '.join(self.options)}" if self.options else ""
            raise ValueError(
                f"unknown parameter {', '.join(map(repr, unknown))} for system '{self.name}' "
                f"(parameters: {known}{opts})"
            )
        self.params: dict[str, float] = {
            key: float(params.get(key, value)) for key, value in self.defaults.items()
        }

    @property
    def node_dim(self) -> int:
        """D, the size of one node's state."""
        return len(self.state_names)

    @property
    def control_dim(self) -> int:
        """U, the size of one node's control (0 for autonomous systems)."""
        return len(self.control_names)

    def scalar_params(self) -> dict[str, float]:
        """The scalar parameters by their ASCII names (a copy)."""
        return dict(self.params)

    def graph(self, topology: str, n: int, seed: int) -> np.ndarray:
        """This system's graph of the given topology and size.

        Args:
            topology: one of `self.topologies` (a user's edge list is read by
                `mpnode_cli.graphs.read_edge_list` instead).
            n: number of nodes.
            seed: graph seed.

        Returns:
            uint8 `[n, n]` adjacency, `A[i, j] = 1` iff j sends to i.

        Raises:
            ValueError: a topology this system does not use, or a size it cannot have.
        """
        if topology not in self.topologies:
            raise ValueError(
                f"system '{self.name}' has no topology '{topology}' "
                f"(choose from: {', '.join(self.topologies)}, or an edge list)"
            )
        return make_graph(topology, n, seed, **self.graph_kwargs(topology, n))

    def graph_kwargs(self, topology: str, n: int) -> dict[str, float]:
        """The `make_graph` parameters this system uses for `topology` at size `n`."""
        return {}

    def graph_params(
        self, adjacency: np.ndarray, rng: np.random.Generator
    ) -> dict[str, np.ndarray]:
        """Parameters drawn once per graph (e.g. Lorenz coupling); none by default.

        Args:
            adjacency: `[N, N]` the graph.
            rng: the generator to draw from.

        Returns:
            name → float64 array; the dataset stacks them with a leading `[G]` axis.
        """
        return {}

    @abstractmethod
    def sample_initial(self, adjacency: np.ndarray, k: int, rng: np.random.Generator) -> np.ndarray:
        """Draw `k` initial states on the graph `adjacency` `[N, N]`.

        Returns:
            float64 `[k, N, D]`.
        """

    @abstractmethod
    def rhs(self, adjacency: torch.Tensor, params: dict[str, torch.Tensor]) -> RHS:
        """The batched vector field for K trajectories.

        Args:
            adjacency: `[K, N, N]` float64, the graph of each trajectory, or `[1, N, N]`
                when all K trajectories share one graph (the generator's usual case).
            params: `graph_params` of each trajectory's graph, stacked on a leading `[K]`
                axis (e.g. `coupling: [K, 3N, 3N]`), or `[1, ...]` when shared.

        Returns:
            `f(t, y)` with `t: [K]`, `y: [K, N, D]` → `dy/dt: [K, N, D]`; pure torch, with
            no Python loop over K and no side effects.
        """

    def reject(self, states: np.ndarray) -> np.ndarray:
        """Which solved trajectories to discard and redraw; none by default.

        Args:
            states: `[K, T, N, D]`.

        Returns:
            bool `[K]`.
        """
        return np.zeros(states.shape[0], dtype=bool)

    def __repr__(self) -> str:
        args = [f"{key}={value:g}" for key, value in self.params.items()]
        args += [f"{key}={getattr(self, key)!r}" for key in self.options]
        return f"{type(self).__name__}({', '.join(args)})"


def neighbour_sum(adjacency: torch.Tensor, x: torch.Tensor) -> torch.Tensor:
    """Σ_j A_ij x_j for every trajectory.

    Args:
        adjacency: `[K, N, N]` per trajectory, or `[1, N, N]` shared by all.
        x: `[K, N, D]`.

    Returns:
        `[K, N, D]`.
    """
    if adjacency.shape[0] == 1 and x.shape[0] != 1:
        # One shared graph: a single (K·D, N) @ (N, N) product. A broadcast `adjacency @ x`
        # runs a batched matmul over an expanded (stride-0) operand, ~100× slower on CPU.
        return (x.transpose(1, 2) @ adjacency[0].T).transpose(1, 2)
    return adjacency @ x
