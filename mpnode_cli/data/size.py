"""What a job will take before it runs: the one size estimate of `generate` and `simulate`.

A job is K trajectories × T samples × N nodes of D states, solved in batches of B
trajectories with some number of solver steps. `SizeEstimate` holds what that costs: the
file, the peak memory, the solver steps per trajectory and a rough time. `check_job`
refuses, before anything is allocated, a job whose memory exceeds what this process may
still take (`mpnode_cli.memory.available_memory`), or whose fixed steps (`--fixed-dt`)
exceed the solver's `max_steps` (every trajectory would stop there, unfinished). The CLI
prints the estimate of a big or slow job and asks before a very big one
(`cli.common.confirm_size`).

The time is a rough guide, measured on a shared 2-core machine: a right-hand-side
evaluation costs `_SECONDS_PER_EVAL` for the batch plus `_SECONDS_PER_VALUE` per node state
and `_SECONDS_PER_MESSAGE` per message of its graphs, and networkx builds a graph at
`_SECONDS_PER_BUILT_MESSAGE` per message. An adaptive solver takes as many steps as the
dynamics need, so its steps are counted as one per sample (at least `_ADAPTIVE_STEPS`),
and the estimate is then a guess within a factor of a few.
"""

from __future__ import annotations

import math
import shutil
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

from mpnode_cli.graphs.matrices import DENSE_GRAPH_MAX_NODES
from mpnode_cli.graphs.topologies import expected_messages
from mpnode_cli.memory import available_memory, format_bytes, format_seconds

if TYPE_CHECKING:
    from mpnode_cli.config.generate import GenerateConfig
    from mpnode_cli.solver.options import SolverOptions

# Bytes per float64 value a chunk's solve holds besides its output (the stages and the
# step's temporaries, for a 7-stage method), per node state.
_SOLVE_WORK = 16 * 8
# Messages per node assumed for a graph whose size cannot be told before it is built (a
# system's own `graph`): mean degree 32, far above the sparse topologies' 4-10, so that the
# estimate errs on the large side.
_EDGES_PER_NODE = 32
# networkx holds a graph as dicts of dicts: about this many bytes per message while it
# builds one (measured ≈ 120 with networkx 3.6; rounded up).
_BUILD_BYTES_PER_MESSAGE = 200
# What a rollout holds per predicted number (a state, message or control component of one
# node at one sample: the batch's float32 outputs and their gather, the float64 copies
# collected and joined, the cast for storage), and per trajectory and sample whatever the
# node count (the interpolant's weights and output indices of the steps that write it).
# Peaks of `mpnode simulate` measured with Tsit5 on 3 and 30 nodes fit ≈ 31 and ≈ 220
# bytes; rounded up, so that the estimate errs on the large side.
_BYTES_PER_VALUE = 48
_BYTES_PER_SAMPLE = 256
# The time model (see the module docstring); `mpnode generate` runs on a busy 2-core
# machine: Lorenz on 3 nodes ≈ 0.4 ms per evaluation, gene on 900 nodes ≈ 50 ns per message.
_SECONDS_PER_EVAL = 4e-4
_SECONDS_PER_VALUE = 1e-7
_SECONDS_PER_MESSAGE = 5e-8
_SECONDS_PER_BUILT_MESSAGE = 5e-6
# What generate holds per trajectory besides its values (its draws, status, evaluation
# count and rows in the solve's records): ≈ 400 bytes measured with 30,000 and 90,000 Lorenz
# trajectories of 11 samples on 3 nodes, and 18 MiB more whatever K; rounded up.
_BYTES_PER_TRAJECTORY = 2048
# Adaptive steps a solve is assumed to take at least, whatever the samples (a gene
# dataset of 2 samples took 36 at the default tolerances).
_ADAPTIVE_STEPS = 30


@dataclass(frozen=True)
class SizeEstimate:
    """What a job will take, before it runs.

    Attributes:
        file_bytes: the file written (states, controls, graphs; a simulation's messages).
        memory_bytes: peak memory (approximate, on the large side).
        values: numbers in `states` (K·T·N·D).
        steps: solver steps per trajectory (exact for fixed steps; a guess for adaptive
            ones, which take what the dynamics need: `solver_steps`).
        seconds: a rough time, or None where there is no model of it.
        fixed: whether `steps` are fixed steps (`--fixed-dt`).
    """

    file_bytes: int
    memory_bytes: int
    values: int
    steps: int = 0
    seconds: float | None = None
    fixed: bool = False

    def describe(self) -> str:
        """`file about 2 MiB, memory about 1.2 GiB, 5000 solver steps per trajectory,
        time roughly 3 min`: what the CLI prints before a big or slow job."""
        text = (f"file about {format_bytes(self.file_bytes)}, memory about "
                f"{format_bytes(self.memory_bytes)}")
        if self.fixed:
            text += f", {self.steps:,} fixed steps per trajectory"
        if self.seconds is not None:
            text += f", time roughly {format_seconds(self.seconds)}"
        return text


def solver_steps(solver: SolverOptions | None, dt: float, samples: int) -> tuple[int, bool]:
    """`(steps per trajectory, fixed)` over `samples` samples `dt` apart: with
    `solver.fixed_dt`, the fixed steps (`mpnode_cli.solver.fixed.fixed_grid`'s count, each
    sample interval cut into equal steps of at most fixed_dt); else a guess, one per
    sample and at least `_ADAPTIVE_STEPS`."""
    intervals = max(samples - 1, 1)
    if solver is None or solver.fixed_dt is None:
        return max(intervals, _ADAPTIVE_STEPS), False
    per_interval = max(1, math.ceil(dt / solver.fixed_dt - 1e-9))
    return intervals * per_interval, True


def check_job(size: SizeEstimate, what: str, advice: str, *,
              solver: SolverOptions | None = None) -> None:
    """Refuse a job that cannot finish: more memory than this process may take, or more
    fixed steps than the solver's `max_steps`.

    Args:
        size: the job's estimate. what: the job, as the message names it ("this dataset").
        advice: what to change to make it smaller ("lower --t-end or raise --dt").
        solver: the job's solver options (their `max_steps`).

    Raises:
        ValueError: the job would not fit or not finish (one line).
    """
    if size.fixed and solver is not None:
        check_steps(size.steps, solver)
    check_memory(size, what, advice)


def check_steps(steps: int, solver: SolverOptions) -> None:
    """Refuse fixed steps (`steps` per trajectory, `solver_steps`) beyond the solver's
    `max_steps`: every trajectory would stop there, unfinished, after all that work.

    Raises:
        ValueError: too many steps (one line, saying which --fixed-dt would do).
    """
    if solver.fixed_dt is None or steps <= solver.max_steps:
        return
    enough = solver.fixed_dt * steps / solver.max_steps  # steps ∝ 1 / fixed_dt
    raise ValueError(
        f"--fixed-dt {solver.fixed_dt:g} takes {steps:,} steps per trajectory, more than "
        f"the solver's max_steps ({solver.max_steps:,}), so every trajectory would stop "
        f"unfinished: raise --fixed-dt (to at least {enough:.2g}), or leave it out for "
        "adaptive steps")


def check_memory(size: SizeEstimate, what: str, advice: str) -> None:
    """Refuse a job whose memory estimate exceeds what this process may still take.

    Raises:
        ValueError: the job would not fit (one line).
    """
    need, have = size.memory_bytes, available_memory()
    if have is not None and need > have:
        raise ValueError(f"{what} needs about {format_bytes(need)} of memory, more than the "
                         f"{format_bytes(have)} this machine has available: {advice}")


def check_disk(size: SizeEstimate, path: Path, what: str) -> None:
    """Refuse a job whose file would not fit in the space free beside `path`, before the
    work that would be lost when writing it fails.

    Raises:
        ValueError: the file would not fit (one line).
    """
    try:
        have = shutil.disk_usage(Path(path).parent).free
    except OSError:  # no figure to compare with: the write itself says it, if it fails
        return
    if size.file_bytes > have:
        raise ValueError(f"{what} needs about {format_bytes(size.file_bytes)} on disk, more "
                         f"than the {format_bytes(have)} free where {path} goes: free some "
                         "space, or write it elsewhere")


def graph_messages(system: Any, config: GenerateConfig) -> int:
    """Messages (directed edges) of one of the config's graphs, before it is built: the
    topology's expected count for the system's parameters of it, an upper bound for an edge
    list (from its file size), `_EDGES_PER_NODE` per node where neither is known; plus
    the edges `--hubs` adds (times `--hub-multiplicity`)."""
    n = config.nodes
    if config.edge_list is not None:  # each line `i j` takes at least 4 bytes
        lines = Path(config.edge_list).stat().st_size // 4
        return min(2 * lines, n * (n - 1))
    w = config.hub_multiplicity  # `--hubs`: each joined to all others, both ways, w times
    hubs = 2 * config.hubs * (n - 1) * w
    try:
        drawn = expected_messages(config.topology, n, **system.graph_kwargs(config.topology, n))
    except Exception:  # a system's own graphs: their size is its own business
        drawn = n * _EDGES_PER_NODE
    return min(drawn + hubs, n * (n - 1) * w)


def generate_estimate(config: GenerateConfig, system: Any, k: int) -> SizeEstimate:
    """The estimate of generating `k` trajectories of a resolved config with `system`
    (its `state_names`, `control_names`, `sparse` and `graph_kwargs`).

    Memory: the float64 states of every trajectory and their cast for storage, each
    trajectory's bookkeeping (`_BYTES_PER_TRAJECTORY`), the graphs (`[G, N, N]` matrices up
    to `DENSE_GRAPH_MAX_NODES` nodes, edge lists above, with networkx's transient build of
    one), and one chunk's solve.
    """
    t, n, g = config.num_steps + 1, config.nodes, config.graphs
    d, u = len(system.state_names), len(system.control_names)
    store = 4 if config.dtype == "float32" else 8
    values = k * t * n * (d + u)
    chunk = min(config.chunk_size, k)
    # Chunks over several graphs carry one float64 copy of the adjacency per trajectory.
    chunk_graphs = chunk if g > 1 else 1
    messages = graph_messages(system, config)
    built = 0 if config.edge_list is not None else messages * _BUILD_BYTES_PER_MESSAGE
    if n <= DENSE_GRAPH_MAX_NODES or not system.sparse:  # matrices
        graph_memory, graph_file = g * n * n * 9 + chunk_graphs * n * n * 8, g * n * n
    else:  # int64 senders and receivers, and a chunk's flattened copy of them
        graph_memory, graph_file = (g + chunk_graphs) * messages * 16, g * messages * 8
    memory = (values * (8 + store) + graph_memory + chunk * n * d * _SOLVE_WORK
              + k * _BYTES_PER_TRAJECTORY)
    steps, fixed = solver_steps(config.solver, config.dt, t)
    seconds = (_solve_seconds(config.solver, steps, k, chunk, n * d, messages)
               + (g * messages * _SECONDS_PER_BUILT_MESSAGE if built else 0.0))
    return SizeEstimate(file_bytes=values * store + graph_file,
                        memory_bytes=memory + built, values=k * t * n * d,
                        steps=steps, seconds=seconds, fixed=fixed)


def _solve_seconds(solver: SolverOptions | None, steps: int, k: int, batch: int,
                   node_values: int, messages: int) -> float:
    """The time model's solve: `steps` steps of every batch of `batch` of the `k`
    trajectories, each step the method's stages of evaluations."""
    from mpnode_cli.solver.tableau import get_method

    stages = get_method(solver.method, solver.fixed_dt).stages if solver else 7
    per_eval = _SECONDS_PER_EVAL + batch * (node_values * _SECONDS_PER_VALUE
                                            + messages * _SECONDS_PER_MESSAGE)
    return math.ceil(k / max(batch, 1)) * steps * stages * per_eval


def simulate_estimate(ckpt: Any, k: int, t: int, n: int, dtype: str = "float32", *,
                      batch_size: int = 128, solver: SolverOptions | None = None,
                      dt: float | None = None) -> SizeEstimate:
    """What rolling a checkpoint's model out for `k` trajectories of `t` samples on `n`
    nodes will take (approximate, on the large side), before anything is allocated.

    The states, the messages of a model that has them and the controls of one that takes
    them are held for every trajectory at once (`roll_out` returns them all), so memory
    grows with K·T·N; the graphs, read already, are not counted. An ensemble of S members
    also holds its members' spread for every trajectory, and its other S − 1 members'
    states and messages for one batch (`batch_size` trajectories) while it is rolled out.
    With `solver` and `dt`, its steps per trajectory (no time: a model's cost per
    evaluation is its own).
    """
    config = ckpt.model_config
    d, m, u = (int(config.get(key) or 0) for key in ("node_dim", "message_dim", "control_dim"))
    s = ckpt.members
    spread = d if s > 1 else 0  # an ensemble's hidden/ensemble_std
    values = k * t * n * (d + m + u + spread)
    batch = (s - 1) * min(k, batch_size) * t  # the other members' samples of one batch
    store = 4 if dtype == "float32" else 8
    steps, fixed = solver_steps(solver, dt or 0.0, t) if dt else (max(t - 1, 1), False)
    return SizeEstimate(file_bytes=values * store,
                        memory_bytes=(values + batch * n * (d + m)) * _BYTES_PER_VALUE
                        + (k * t + batch) * _BYTES_PER_SAMPLE,
                        values=k * t * n * d, steps=steps, fixed=fixed)
