"""The interface every dynamical system on a graph implements.

A system is homogeneous: N identical nodes, each with a D-dimensional state
(`state_names`), coupled along a graph. Generating data for it takes five pieces, one
method each: its graph (`graph`), the parameters drawn once per graph (`graph_params`),
initial states (`sample_initial`), a batched torch right-hand side (`rhs`), and an optional
filter of trajectories to redraw (`reject`).

Two hooks serve systems that are more than an autonomous ODE on the nodes (the quadrotor
swarm: a closed-loop flight with controls, a hidden load and per-flight plans):
`sample` draws initial states together with per-trajectory inputs, and `simulate` turns
them into a `Simulation` (states, optional controls and hidden states, solver status, and
the system's own rejections). Their defaults are `sample_initial` and one `solve` of `rhs`.

Systems know nothing of files. torch and the solver are imported inside methods so that
importing the registry (for the CLI's choices) stays cheap.
"""

from __future__ import annotations

import itertools
from abc import ABC, abstractmethod
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, ClassVar

import numpy as np

from mpnode_cli.graphs import make_graph

if TYPE_CHECKING:
    import torch

    from mpnode_cli.solver.options import SolverOptions

RHS = Callable[["torch.Tensor", "torch.Tensor"], "torch.Tensor"]


@dataclass(frozen=True)
class Simulation:
    """What `System.simulate` returns for B trajectories (torch tensors).

    Attributes:
        states: `[B, T, N, D]` float64 node states at the output times; NaN after a failure.
        status: `[B]` int, a `mpnode_cli.solver.Status` per trajectory (0 = finished).
        n_f_evals: `[B]` int, right-hand-side evaluations spent on each trajectory.
        controls: `[B, T, N, U]` zero-order-hold controls (`controls[:, k]` acts on
            `[t_k, t_k+1)`), or None for an autonomous system.
        hidden: unobserved states besides the nodes, name → `[B, T, ...]`.
        rejected: `[B]` bool, trajectories the system itself discards (checks that need
            more than the stored states, e.g. between samples), or None.
        diagnostics: name → `[B]` per-trajectory figures behind `rejected` (for reports
            and tests; not stored).
    """

    states: torch.Tensor
    status: torch.Tensor
    n_f_evals: torch.Tensor
    controls: torch.Tensor | None = None
    hidden: dict[str, torch.Tensor] = field(default_factory=dict)
    rejected: torch.Tensor | None = None
    diagnostics: dict[str, torch.Tensor] = field(default_factory=dict)


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
    # How to learn this system (written into each dataset as its `recipe` attribute; see
    # `mpnode_cli.training.recipe` and docs/training-recipe.md): the paper's training loss
    # for it, and train-config fields mpnode's own recipe sets for it.
    paper_loss: ClassVar[str] = "mse"
    recommended: ClassVar[dict[str, object]] = {}

    @classmethod
    def recipe(cls) -> dict[str, dict[str, object]]:
        """`{"paper": {...}, "mpnode": {...}}`: train-config fields this system recommends."""
        return {"paper": {"loss": cls.paper_loss}, "mpnode": dict(cls.recommended)}

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
                when all K trajectories share one graph (the generator's usual case). With
                several graphs the generator keeps each graph's trajectories in one block,
                which `NeighbourSum` turns into one product per graph.
            params: `graph_params` of each trajectory's graph, stacked on a leading `[K]`
                axis (e.g. `coupling: [K, 3N, 3N]`), or `[1, ...]` when shared.

        Returns:
            `f(t, y)` with `t: [K]`, `y: [K, N, D]` → `dy/dt: [K, N, D]`; pure torch, with
            no Python loop over K and no side effects.
        """

    def sample(
        self, adjacency: np.ndarray, k: int, rng: np.random.Generator
    ) -> tuple[np.ndarray, dict[str, np.ndarray]]:
        """Draw `k` initial states and the per-trajectory inputs `simulate` needs.

        Args:
            adjacency: `[N, N]` the graph.
            k: number of trajectories.
            rng: the generator to draw from.

        Returns:
            `(y0 float64 [k, N, D], inputs: name → [k, ...])`; by default `sample_initial`
            and no inputs (so the random stream is exactly `sample_initial`'s).
        """
        return self.sample_initial(adjacency, k, rng), {}

    def simulate(
        self,
        adjacency: torch.Tensor,
        params: dict[str, torch.Tensor],
        y0: torch.Tensor,
        ts: torch.Tensor,
        inputs: dict[str, torch.Tensor],
        *,
        solver: SolverOptions,
        progress: Callable[[float], None] | None = None,
    ) -> Simulation:
        """Trajectories from `y0` sampled at `ts`; by default one float64 solve of `rhs`.

        Args:
            adjacency, params: as for `rhs` (`[1, ...]` shared or `[B, ...]`).
            y0: `[B, N, D]` float64 initial states.
            ts: `[T]` float64 output times.
            inputs: `sample`'s per-trajectory inputs, each `[B, ...]` (none by default).
            solver: how to integrate (the generate config's `solver`).
            progress: called now and then with the fraction of the horizon simulated.

        Returns:
            A `Simulation`.
        """
        from mpnode_cli.solver import solve

        sol = solve(self.rhs(adjacency, params), y0, ts, **solver.solve_kwargs(),
                    progress=progress)
        return Simulation(states=sol.ys, status=sol.status, n_f_evals=sol.stats["n_f_evals"])

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

    The result equals `adjacency @ x` up to rounding (summation order inside the GEMM).
    """

    def __init__(self, adjacency: torch.Tensor) -> None:
        """Plan the product.

        Args:
            adjacency: `[K, N, N]` per trajectory, or `[1, N, N]` shared by all (also any
                `[K, M, M]` matrices acting on `[K, M, D]`, e.g. Lorenz's coupling H).
        """
        import torch

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
