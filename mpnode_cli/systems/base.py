"""The interface every dynamical system on a graph implements, built in or your own.

A system is homogeneous: N identical nodes, each with a D-dimensional state
(`state_names`), coupled along a graph. Generating data for it takes five pieces, one
method each: its graph (`graph`), the parameters drawn once per graph (`graph_params`),
initial states (`sample_initial`), a batched torch right-hand side (`rhs`), and an optional
filter of trajectories to redraw (`reject`).

A system declares what `mpnode generate` needs to know about it, so that neither the CLI
nor the presets hold per-system knowledge: its scalar parameters and their defaults
(`defaults`), its options (`options`: `Option` declarations with
defaults, help and allowed values; the CLI's "System options" are built from them), its
data defaults (`data_defaults`: trajectories, horizon, spacing) and its named datasets
(`presets`). A system of your own subclasses `System` in a Python file
(`mpnode generate --system-file FILE`) or a package (entry point group `mpnode.systems`);
docs/custom-systems.md walks through one.

Two hooks serve systems that are more than an autonomous ODE on the nodes (the quadrotor
swarm: a closed-loop flight with controls, a hidden load and per-flight plans):
`sample` draws initial states together with per-trajectory inputs, and `simulate` turns
them into a `Simulation` (states, optional controls and hidden states, solver status, and
the system's own rejections). Their defaults are `sample_initial` and one `solve` of `rhs`.

Graphs of at most `mpnode_cli.limits.DENSE_GRAPH_MAX_NODES` nodes reach a system as
matrices: `[N, N]` ndarrays for `graph_params` and `sample`, `[K, N, N]` (or `[1, N, N]`)
tensors for `rhs`. Larger graphs reach only systems that declare `sparse = True`, as an
`EdgeList` (which has the matrix's `shape`, so code that only reads N takes either) and an
`EdgeBatch` for `rhs`; `NeighbourSum` takes both forms, so a system whose coupling is a
neighbour sum runs on either without knowing which.

Systems know nothing of files. torch and the solver are imported inside methods so that
importing the registry (for the CLI's choices) stays cheap.
"""

from __future__ import annotations

import math
from abc import ABC, abstractmethod
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, ClassVar

import numpy as np

from mpnode_cli.graphs.matrices import DENSE_GRAPH_MAX_NODES, EdgeBatch, EdgeList
from mpnode_cli.graphs.topologies import make_edges, make_graph
from mpnode_cli.systems.neighbour_sum import NeighbourSum  # noqa: F401  (older plug-ins)

if TYPE_CHECKING:
    import torch

    from mpnode_cli.solver.options import SolverOptions

RHS = Callable[["torch.Tensor", "torch.Tensor"], "torch.Tensor"]


@dataclass(frozen=True)
class Option:
    """A system option that is not a physical parameter (e.g. the initial-state box).

    Attributes:
        default: its value when not given: a number, or a string among `choices`.
        help: one line for `mpnode generate --help` and error messages.
        choices: the allowed strings (empty: a number).
        minimum: the smallest allowed number (None: any finite number).
    """

    default: float | str
    help: str
    choices: tuple[str, ...] = ()
    minimum: float | None = None

    def parse(self, value: object, name: str, system: str) -> float | str:
        """`value` checked against this declaration (numbers as float).

        Raises:
            ValueError: a value outside `choices`, not a number, or below `minimum`.
        """
        if self.choices:
            if value not in self.choices:
                raise ValueError(f"unknown {name} '{value}' for {system} (choose from: "
                                 f"{', '.join(self.choices)})")
            return str(value)
        try:
            number = float(value)  # type: ignore[arg-type]
        except (TypeError, ValueError):
            raise ValueError(f"{system} option {name} must be a number, got {value!r}") from None
        if not math.isfinite(number) or (self.minimum is not None and number < self.minimum):
            low = "" if self.minimum is None else f" >= {self.minimum:g}"
            raise ValueError(f"{system} option {name} must be a finite number{low}, "
                             f"got {value!r} ({self.help})")
        return number


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

    Subclasses set the class attributes below and implement `sample_initial` and `rhs`.

    Class attributes:
        name: registry name (`mpnode generate NAME`, the dataset's `system`).
        state_names: `[D]` names of a node's state components.
        periodic_states: the names among `state_names` that are angles, whose dynamics are
            2π-periodic in them (Kuramoto's phases, a pendulum's θ). Datasets record them
            (`periodic_states`, docs/dataset-format.md); MP-NODE's `--periodic embed` feeds
            its networks (sin θ, cos θ) for them, and `--wrap-angles` measures their errors
            mod 2π. Empty (the default): no state is an angle.
        control_names: `[U]` names of a node's controls (none for an autonomous system).
        topologies: the `mpnode_cli.graphs.topologies.make_graph` topologies it runs on;
            default_topology and default_nodes: the graph without options.
        defaults: scalar parameters and their default values (written as attributes of
            the dataset's `params` group; given as `-p NAME=VALUE`).
        options: options that are not physical parameters, name → `Option`; each is
            stored on the instance as an attribute of its name.
        data_defaults: `trajectories`, `t_end` and `dt` of `mpnode generate NAME` without
            a preset (the authors' Lorenz sizes unless a system says otherwise).
        presets: named datasets, name → partial generate config (`system` is added);
            `mpnode generate --preset NAME`.
        paper_loss, recommended: how to learn it (see `recipe`).
        sparse: runs on graphs given as edge lists (`EdgeList`, `EdgeBatch`), hence on
            graphs above `DENSE_GRAPH_MAX_NODES` nodes; a system that needs the matrix
            itself (Lorenz's coupling H is `[3N, 3N]`) leaves it False and is refused there.
        grid_layout: its nodes sit on a square grid (gene's hot-spot initial states), so
            `--grid SIDE` (N = SIDE²) means something for it; any other system refuses
            `grid`, which would only be a roundabout node count.
    """

    name: ClassVar[str]
    state_names: ClassVar[tuple[str, ...]]
    periodic_states: ClassVar[tuple[str, ...]] = ()
    control_names: ClassVar[tuple[str, ...]] = ()
    topologies: ClassVar[tuple[str, ...]]
    default_topology: ClassVar[str]
    default_nodes: ClassVar[int]
    defaults: ClassVar[dict[str, float]]
    options: ClassVar[dict[str, Option]] = {}
    # The authors' data defaults (MPNODE.jl configs/empode_sys_32_3.toml).
    data_defaults: ClassVar[dict[str, float]] = {"trajectories": 1000, "t_end": 2.5,
                                                 "dt": 0.05}
    presets: ClassVar[dict[str, dict[str, object]]] = {}
    # How to learn this system (written into each dataset as its `recipe` attribute; see
    # `mpnode_cli.training.recipe` and docs/training-recipe.md): the paper's training loss
    # for it, and train-config fields mpnode's own recipe sets for it.
    paper_loss: ClassVar[str] = "mse"
    recommended: ClassVar[dict[str, object]] = {}
    sparse: ClassVar[bool] = False
    grid_layout: ClassVar[bool] = False

    @classmethod
    def recipe(cls) -> dict[str, dict[str, object]]:
        """`{"paper": {...}, "mpnode": {...}}`: train-config fields this system recommends."""
        return {"paper": {"loss": cls.paper_loss}, "mpnode": dict(cls.recommended)}

    def __init__(self, **given: float | str) -> None:
        """Set the scalar parameters and the options, each defaulting to its declaration.

        Raises:
            ValueError: a key that is neither a parameter nor an option of this system, a
                parameter that is not a finite number, or an option its `Option` refuses.
        """
        unknown = sorted(set(given) - set(self.defaults) - set(self.options))
        if unknown:
            known = ", ".join(self.defaults) or "none"
            opts = f"; options: {', '.join(self.options)}" if self.options else ""
            raise ValueError(
                f"unknown parameter {', '.join(map(repr, unknown))} for system '{self.name}' "
                f"(parameters: {known}{opts})"
            )
        self.params: dict[str, float] = {}
        for key, value in self.defaults.items():
            try:
                number = float(given.get(key, value))
            except (TypeError, ValueError):
                number = math.nan
            if not math.isfinite(number):
                raise ValueError(f"{self.name} parameter {key} must be a finite number, got "
                                 f"{given.get(key)!r}")
            self.params[key] = number
        for key, option in self.options.items():
            setattr(self, key, option.parse(given.get(key, option.default), key, self.name))

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

    def graph(self, topology: str, n: int, seed: int) -> np.ndarray | EdgeList:
        """This system's graph of the given topology and size.

        Args:
            topology: one of `self.topologies` (a user's edge list is read by
                `mpnode_cli.graphs.edge_files.read_edge_list` instead).
            n: number of nodes.
            seed: graph seed.

        Returns:
            uint8 `[n, n]` adjacency, `A[i, j] = 1` iff j sends to i, for n ≤
            `DENSE_GRAPH_MAX_NODES`; above, the same graph as an `EdgeList` (no matrix).

        Raises:
            ValueError: a topology this system does not use, or a size it cannot have.
        """
        if topology not in self.topologies:
            raise ValueError(
                f"system '{self.name}' has no topology '{topology}' "
                f"(choose from: {', '.join(self.topologies)}, or an edge list)"
            )
        build = make_graph if n <= DENSE_GRAPH_MAX_NODES else make_edges
        return build(topology, n, seed, **self.graph_kwargs(topology, n))

    def graph_kwargs(self, topology: str, n: int) -> dict[str, float]:
        """The `make_graph` parameters this system uses for `topology` at size `n`."""
        return {}

    def graph_params(
        self, adjacency: np.ndarray, rng: np.random.Generator
    ) -> dict[str, np.ndarray]:
        """Parameters drawn once per graph (e.g. Lorenz coupling); none by default.

        Args:
            adjacency: `[N, N]` the graph (an `EdgeList` above `DENSE_GRAPH_MAX_NODES` nodes).
            rng: the generator to draw from.

        Returns:
            name → float64 array; the dataset stacks them with a leading `[G]` axis.
        """
        return {}

    @abstractmethod
    def sample_initial(self, adjacency: np.ndarray, k: int, rng: np.random.Generator) -> np.ndarray:
        """Draw `k` initial states on the graph `adjacency` `[N, N]` (or `EdgeList`).

        Returns:
            float64 `[k, N, D]`.
        """

    @abstractmethod
    def rhs(self, adjacency: torch.Tensor | EdgeBatch,
            params: dict[str, torch.Tensor]) -> RHS:
        """The batched vector field for K trajectories.

        Args:
            adjacency: `[K, N, N]` float64, the graph of each trajectory, or `[1, N, N]`
                when all K trajectories share one graph (the generator's usual case). With
                several graphs the generator keeps each graph's trajectories in one block,
                which `NeighbourSum` turns into one product per graph. Above
                `DENSE_GRAPH_MAX_NODES` nodes (`sparse` systems only) an `EdgeBatch` of
                batch K, or 1 when shared.
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
            adjacency: `[N, N]` the graph (an `EdgeList` above `DENSE_GRAPH_MAX_NODES` nodes).
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
        from mpnode_cli.systems.plugin_calls import checked_rhs

        # Checked: a vector field of the wrong shape is one line naming it, not an error
        # from deep inside the solver's stage sums.
        sol = solve(checked_rhs(self, self.rhs(adjacency, params)), y0, ts,
                    **solver.solve_kwargs(), progress=progress)
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
