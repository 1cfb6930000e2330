"""N quadrotors carrying a cable-suspended load through a doorway (paper §4, App. A.5).

The paper's hardest system: the authors generated it with the trajectory optimizer of Jackson
et al. (RA-L 2020) and never released a generator; this is a self-contained closed-loop one
(physics in `quadrotor_dynamics`, reference and controller in `quadrotor_control`, the
design and its checks in `docs/quadrotor.md`). Parameters are the RA-L code's
(RoboticExplorationLab/TrajectoryOptimization.jl, `examples/RA-L/models.jl`).

Dataset: node = quadrotor, state 13 (r, q scalar first, v world, ω body), control 5 (the
four rotor forces and the cable tension, each the mean over the 0.2 s sample interval),
complete graph among the quads. The load (state 6) is not a node: the paper couples the
quads through it unobserved, so it is stored as `hidden/load [K, T, 6]`, with the planned
load path as `hidden/load_reference [K, T, 3]` (its last sample is the goal).

A flight is rejected and redrawn when, at any 0.01 s control update, a cable's length is
off by 1 cm or more, a quad (sphere of 0.275 m, the authors' radius), the load (0.2 m) or
a cable enters a doorway cylinder, a quad or the load leaves 0 ≤ z ≤ 2.1 (the authors'
bounds), two quads come closer than 0.55 m; or when the load ends more than 0.3 m from its
goal, or a rotor is saturated at 5 % or more of the control updates.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import TYPE_CHECKING, ClassVar

import numpy as np

from mpnode_cli.systems.base import RHS, Simulation, System

if TYPE_CHECKING:
    import torch

    from mpnode_cli.solver.options import SolverOptions

# Swarm sizes whose fold is collision-free and keeps every cable taut (see `Reference`): odd
# sizes have no opposite pairs, and five quads do not fold without meeting.
NODE_COUNTS = (3, 4, 6)


class Quadrotor(System):
    """Quadrotors lifting a load through a doorway (Gupta et al. 2022, App. A.5)."""

    name: ClassVar[str] = "quadrotor"
    state_names: ClassVar[tuple[str, ...]] = (
        "x", "y", "z", "qw", "qx", "qy", "qz", "vx", "vy", "vz", "wx", "wy", "wz",
    )  # fmt: skip
    control_names: ClassVar[tuple[str, ...]] = ("w1", "w2", "w3", "w4", "tension")
    topologies: ClassVar[tuple[str, ...]] = ("complete",)
    default_topology: ClassVar[str] = "complete"
    default_nodes: ClassVar[int] = 3
    defaults: ClassVar[dict[str, float]] = {
        "m": 1.0, "Jxx": 0.0023, "Jyy": 0.0023, "Jzz": 0.004, "arm": 0.175, "km": 0.0245,
        "w_max": 4.66, "m_load": 0.9, "cable": 1.55, "g": 9.81,
    }  # fmt: skip
    # The paper's 463 flights of 10 s sampled every 0.2 s (App. A.5) for three quads; the
    # paper gives no count for six, so `quad6` has 463 as well.
    data_defaults: ClassVar[dict[str, float]] = {"trajectories": 463, "t_end": 10.0,
                                                 "dt": 0.2}
    presets: ClassVar[dict[str, dict[str, object]]] = {
        f"quad{n}": {"nodes": n, "trajectories": 463, "t_end": 10.0, "dt": 0.2}
        for n in (3, 6)}
    # The horizon curriculum, though 51 samples are below the general threshold, and lr
    # 3e-3: on quad3 at 150 epochs, test MSE 0.35 over the whole horizon, 0.25 with the
    # curriculum, 0.14 with both (docs/training-recipe.md).
    # The mean and the paper's MLP update: one shared load on a complete graph, where every
    # node has the same degree.
    recommended: ClassVar[dict[str, object]] = {
        "horizon_curriculum": True, "lr": 3e-3, "model_options": {"aggregate": "mean"}}

    def graph(self, topology: str, n: int, seed: int) -> np.ndarray:
        """The complete graph among `n` quads (n in `NODE_COUNTS`).

        Raises:
            ValueError: another topology or size.
        """
        if n not in NODE_COUNTS:
            raise ValueError(
                f"quadrotor flies {', '.join(map(str, NODE_COUNTS))} quads, not {n}: fewer "
                "cannot hold the load in place, and the doorway fold is planned for these"
            )
        return super().graph(topology, n, seed)

    def rhs(self, adjacency: torch.Tensor, params: dict[str, torch.Tensor]) -> RHS:
        """Not available: a flight is closed-loop, so data come from `simulate`.

        Raises:
            NotImplementedError: always.
        """
        raise NotImplementedError(
            "the quadrotor swarm has no autonomous right-hand side on its nodes (the load is "
            "hidden and the rotor forces come from a controller); use `simulate`, or "
            "`quadrotor_dynamics.swarm_rhs` for the physics with given rotor forces"
        )

    def sample_initial(self, adjacency: np.ndarray, k: int, rng: np.random.Generator) -> np.ndarray:
        """Quads hovering in their circle around a resting load; float64 `[k, N, 13]`."""
        return self.sample(adjacency, k, rng)[0]

    def sample(
        self, adjacency: np.ndarray, k: int, rng: np.random.Generator
    ) -> tuple[np.ndarray, dict[str, np.ndarray]]:
        """Draw k flights: start, goal, circle phase and timing, and the hover they start in.

        Returns:
            `(y0 [k, N, 13], inputs)` with inputs `start [k, 3]`, `goal [k, 3]` (load
            positions), `phase [k]` (rad), `timing [k, 8]` (uniform draws in [0, 1) that
            `quadrotor_flight.plan_reference` turns into seconds).
        """
        import torch

        from mpnode_cli.systems.quadrotor_control import circle_directions, hover_state
        from mpnode_cli.systems.quadrotor_dynamics import QuadParams

        n = adjacency.shape[0]
        start = np.stack(
            [rng.uniform(-0.15, 0.15, k), rng.uniform(-0.1, 0.1, k),
             0.25 + rng.uniform(-0.03, 0.03, k)], axis=1,
        )  # fmt: skip
        goal = np.stack(
            [6.0 + rng.uniform(-0.15, 0.15, k), rng.uniform(-0.1, 0.1, k),
             0.25 + rng.uniform(-0.03, 0.03, k)], axis=1,
        )  # fmt: skip
        phase = rng.uniform(0.0, 2 * math.pi / n, k)  # the circle repeats every 2π/N
        timing = rng.uniform(0.0, 1.0, (k, 8))
        p = QuadParams(self.params)
        circle = circle_directions(torch.from_numpy(phase), n, p.cable)
        quads, _, _ = hover_state(torch.from_numpy(start), circle, p)
        inputs = {"start": start, "goal": goal, "phase": phase, "timing": timing}
        return quads.numpy(), inputs

    def simulate(self, adjacency: torch.Tensor, params: dict[str, torch.Tensor],
                 y0: torch.Tensor, ts: torch.Tensor, inputs: dict[str, torch.Tensor], *,
                 solver: SolverOptions, progress: Callable[[float], None] | None = None,
                 ) -> Simulation:
        """Fly B planned flights closed-loop (`System.simulate`'s arguments); see
        `quadrotor_flight.fly`."""
        from mpnode_cli.systems.quadrotor_flight import fly

        return fly(self.params, y0, ts, inputs, solver=solver, progress=progress)
