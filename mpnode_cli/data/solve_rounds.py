"""Steps 3–4 of `mpnode_cli.data.generate`: solve the drawn trajectories in chunks, and
redraw those the solver could not finish or the system rejects, until none are left.

Samples are independent in the solver, so chunking does not change the results; redraws
come from the draws' own generator, so the same config gives bit-identical states.
"""

from __future__ import annotations

import functools
import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np

from mpnode_cli.config.generate import GenerateConfig
from mpnode_cli.graphs.matrices import Graphs
from mpnode_cli.progress import Progress
from mpnode_cli.systems.contract import CheckedSystem

if TYPE_CHECKING:
    import torch

    from mpnode_cli.systems.base import Simulation

# Redraw rounds before giving up on trajectories that keep failing. A trajectory fails
# independently with probability p per draw (p ≈ 0.2 for the pendulum's wide box), so 50
# rounds only run out when something is systematically wrong.
MAX_REDRAW_ROUNDS = 50


class GenerateError(RuntimeError):
    """Generation could not produce a complete dataset (e.g. every trajectory fails)."""


@dataclass
class Draws:
    """The trajectories a file holds (a shard's: its own), before they are solved.

    Attributes:
        lo, hi: their range in the whole dataset (all K, or a shard's).
        graph_index: `[K]` int32, each trajectory's graph.
        y0: `[K, N, D]` initial states; redraws overwrite rows.
        inputs: name → `[K, ...]` per-trajectory inputs (`System.sample`); redraws
            overwrite rows.
        first_chunks: the first round's solver chunks (`solver_chunks`), numbered in the file.
        rng: the generator redraws come from.
    """

    lo: int
    hi: int
    graph_index: np.ndarray
    y0: np.ndarray
    inputs: dict[str, np.ndarray]
    first_chunks: list[tuple[np.ndarray, int | None]]
    rng: np.random.Generator


@dataclass
class Solved:
    """What the solves gave, per trajectory (`[K, ...]`, each one's last solve), and the
    counts over all rounds.

    Attributes:
        states: `[K, T, N, D]` float64.
        status: `[K]` int8 solver status. n_f_evals: `[K]` int64.
        sim_rejected: `[K]` bool, what the system's simulation rejected.
        controls: `[K, T, N, U]`, allocated by the first chunk with some, or None.
        hidden: name → `[K, T, ...]`.
        rejected, failed: trajectories redrawn because the system rejected them or the
            solver failed. total_f_evals: right-hand-side evaluations of every solve.
        solve_seconds: time spent solving.
    """

    states: np.ndarray
    status: np.ndarray
    n_f_evals: np.ndarray
    sim_rejected: np.ndarray
    controls: np.ndarray | None = None
    hidden: dict[str, np.ndarray] = field(default_factory=dict)
    rejected: int = 0
    failed: int = 0
    total_f_evals: int = 0
    solve_seconds: float = 0.0

    @classmethod
    def empty(cls, k: int, shape: tuple[int, ...]) -> Solved:
        """Nothing solved yet, for k trajectories of `shape` `[T, N, D]` each."""
        return cls(np.empty((k, *shape)), np.zeros(k, dtype=np.int8),
                   np.zeros(k, dtype=np.int64), np.zeros(k, dtype=bool))

    def store(self, chunk: np.ndarray, sim: Simulation) -> None:
        """Keep a chunk's `Simulation` in the rows `chunk`."""
        k = len(self.states)
        self.states[chunk] = sim.states.numpy()
        self.status[chunk] = sim.status.numpy()
        self.n_f_evals[chunk] = sim.n_f_evals.numpy()
        if sim.controls is not None:
            if self.controls is None:
                self.controls = np.empty((k, *sim.controls.shape[1:]))
            self.controls[chunk] = sim.controls.numpy()
        for name, value in sim.hidden.items():
            self.hidden.setdefault(name, np.empty((k, *value.shape[1:])))[chunk] = value.numpy()
        if sim.rejected is not None:
            self.sim_rejected[chunk] = sim.rejected.numpy()


def solve_and_redraw(system: CheckedSystem, config: GenerateConfig, ts: torch.Tensor,
                      graphs: Graphs,
                      params: dict[str, np.ndarray], draws: Draws,
                      progress: Progress | None, stage: Callable[[str], None]) -> Solved:
    """Steps 3–4: solve, then redraw what failed or was rejected, until nothing is left.

    Raises:
        GenerateError: nothing ever succeeds, or trajectories still fail after
            `MAX_REDRAW_ROUNDS` redraws.
    """
    k = draws.hi - draws.lo
    solved = Solved.empty(k, (ts.numel(), *draws.y0.shape[1:]))
    pending, total, done = np.arange(k), k, 0
    solved_any = False
    if progress is not None:
        progress(0, total)
    for round_ in range(MAX_REDRAW_ROUNDS + 1):
        chunks = (draws.first_chunks if round_ == 0
                  else solver_chunks(pending, draws.graph_index, config.chunk_size))
        done = _solve_round(system, config, ts, graphs, params, draws, chunks, solved,
                            (progress, stage), done, total)
        solved.total_f_evals += int(solved.n_f_evals[pending].sum())

        bad_status = solved.status[pending] != 0
        bad_reject = ((system.reject(solved.states[pending]) | solved.sim_rejected[pending])
                      & ~bad_status)  # fmt: skip
        solved_any |= not bad_status.all()
        # Redrawing cannot help when nothing ever succeeds: say why instead of looping.
        if not solved_any and (len(pending) >= 10 or round_ == 2):
            raise GenerateError(_failure_message(solved.status[pending],
                                                 "every trajectory failed"))
        solved.failed += int(bad_status.sum())
        solved.rejected += int(bad_reject.sum())
        pending = pending[bad_status | bad_reject]
        if len(pending) == 0:
            break
        if round_ == MAX_REDRAW_ROUNDS:
            raise GenerateError(
                _failure_message(
                    solved.status[pending],
                    f"{len(pending)} trajectories still failed after {MAX_REDRAW_ROUNDS} redraws",
                )
            )
        for i in np.unique(draws.graph_index[pending]):
            redo = pending[draws.graph_index[pending] == i]
            draws.y0[redo], redo_inputs = system.sample(graphs.graph(i), len(redo), draws.rng)
            for name, value in redo_inputs.items():
                draws.inputs[name][redo] = value
        total += len(pending)
    return solved


def _solve_round(system: CheckedSystem, config: GenerateConfig, ts: torch.Tensor, graphs: Graphs,
                 params: dict[str, np.ndarray], draws: Draws, chunks, solved: Solved,
                 told: tuple[Progress | None, Callable[[str], None]], done: int, total: int) -> int:
    """Solve one round's chunks into `solved`, telling `told` (progress, stage) as they
    go; the progress count `done` after them."""
    progress, stage = told
    for chunk, gi in chunks:
        stage(f"solving trajectories {done + 1}–{done + len(chunk)} of {total}")
        tic = time.perf_counter()
        # `[1, ...]` when the chunk shares one graph, else one copy per trajectory.
        which = slice(gi, gi + 1) if gi is not None else draws.graph_index[chunk]
        chunk_params = {name: value[which] for name, value in params.items()}
        chunk_inputs = {name: value[chunk] for name, value in draws.inputs.items()}
        within = None if progress is None else functools.partial(
            _within_chunk, progress, done, len(chunk), total)
        sim = solve_chunk(system, config, ts, graphs, np.atleast_1d(which if gi is None else gi),
                           chunk_params, draws.y0[chunk], chunk_inputs, within)
        solved.solve_seconds += time.perf_counter() - tic
        solved.store(chunk, sim)
        done += len(chunk)
        if progress is not None:
            progress(done, total)
    return done


def solver_chunks(pending: np.ndarray, graph_index: np.ndarray, size: int):
    """Yield `(trajectory ids, graph id or None)`: at most `size` trajectories at a time.

    With one graph, every chunk shares it (graph id given): the right-hand side then gets
    one adjacency and parameter set (`[1, ...]`) and aggregates with a single matmul. With
    several graphs, chunks mix them (graph id None) and carry per-trajectory copies: one
    batched solve beats one small solve per graph, whose per-step overhead dominates. The
    copies stay in blocks by graph (trajectories are numbered graph by graph and `pending`
    is sorted), so the systems' `NeighbourSum` still does one product per graph.
    """
    graphs = np.unique(graph_index[pending])
    for chunk in np.array_split(pending, math.ceil(len(pending) / size)):
        yield chunk, (int(graphs[0]) if len(graphs) == 1 else None)


def _within_chunk(progress: Progress, done: int, size: int, total: int, frac: float) -> None:
    """Progress inside a chunk: `frac` of its `size` trajectories solved after `done`."""
    progress(done + frac * size, total)


def solve_chunk(system, config, ts, graphs, which, params, y0, inputs, progress=None):
    """Simulate one chunk of trajectories in float64 (`System.simulate`).

    Args:
        graphs: the dataset's graphs; which: `[1]` the chunk's shared graph or `[B]` each
            trajectory's. The system gets float64 `[1 or B, N, N]` matrices up to
            `DENSE_GRAPH_MAX_NODES` nodes, an `EdgeBatch` above.
        params: `[1, ...]` or `[B, ...]`;
        y0: `[B, N, D]`; ts: torch `[T]`; inputs: name → `[B, ...]`.
        progress: called with the fraction of the chunk's horizon solved, or None.

    Returns:
        A `mpnode_cli.systems.base.Simulation`.
    """
    import torch

    def tensor(x: np.ndarray) -> torch.Tensor:
        return torch.from_numpy(np.ascontiguousarray(x))

    graph = (tensor(graphs.dense()[which].astype(np.float64)) if graphs.dense_ok
             else graphs.batch(which))
    return system.simulate(
        graph,
        {name: tensor(v) for name, v in params.items()},
        tensor(y0),
        ts,
        {name: tensor(v) for name, v in inputs.items()},
        solver=config.solver,
        progress=progress,
    )


def _failure_message(status: np.ndarray, what: str) -> str:
    from mpnode_cli.solver import Status

    codes, counts = np.unique(status[status != 0], return_counts=True)
    if len(codes) == 0:
        return f"{what}: the system rejected them (see its `reject`)"
    worst = Status(int(codes[np.argmax(counts)]))
    return f"{what} ({worst.name}): {worst.message}"
