"""Ground truth for a dataset: a system on G graphs, K trajectories, one HDF5 file.

`generate(config)` reads top to bottom:
1. build G graphs (seed `graph_seed + g`) and draw each graph's parameters;
2. spread K trajectories evenly over the graphs (contiguous blocks) and draw their initial
   states (and any per-trajectory inputs, `System.sample`) from
   `np.random.default_rng(seed)`, graph by graph;
3. simulate them all in float64 (`System.simulate`: by default one solve of the system's
   right-hand side with our batched Tsit5), `chunk_size` trajectories at a time (samples
   are independent in the solver, so chunking does not change the results); a system with
   controls or hidden states (the quadrotor swarm) returns those too;
4. redraw trajectories the solver could not finish or the system rejects (e.g. pendulums
   near cos θ = 0, quadrotor flights that break a check), from the same generator, until
   none are left; the counts are stored;
5. split by trajectory with a generator derived from `seed`, and write the file atomically.

The same config gives bit-identical `states`. With `config.shard = (i, n)` the same steps
write shard i of n: all graphs and initial states are drawn, only the shard's solver
chunks are solved, and its redraws come from a generator of its own
(`mpnode_cli.data.shards`). Nothing here prints; progress goes through an optional
callback.
"""

from __future__ import annotations

import json
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from mpnode_cli.config.generate import GenerateConfig
from mpnode_cli.data.shards import (
    SHARD_ATTR,
    redraw_seed,
    shard_attribute,
    shard_chunks,
    shard_path,
    shard_range,
)
from mpnode_cli.data.size import SizeEstimate, check_disk, check_job, generate_estimate
from mpnode_cli.data.solve_rounds import Draws, Solved, solve_and_redraw, solver_chunks
from mpnode_cli.data.solve_rounds import GenerateError as GenerateError  # part of this API
from mpnode_cli.data.splits import split_trajectories
from mpnode_cli.graphs.edge_files import read_edges
from mpnode_cli.graphs.matrices import DENSE_GRAPH_MAX_NODES, EdgeList, Graphs
from mpnode_cli.graphs.topologies import hubs_tag, join_hubs, spread_multiplicity
from mpnode_cli.memory import naming_memory
from mpnode_cli.progress import Progress
from mpnode_cli.systems.contract import CheckedSystem
from mpnode_cli.systems.plugin_calls import named
from mpnode_cli.systems.registry import (
    grid_systems,
    load_system_file,
    sparse_systems,
    system_class,
)

if TYPE_CHECKING:
    import torch


@dataclass(frozen=True)
class GenerateSummary:
    """What `generate` did.

    Attributes:
        path: the file written.
        trajectories: K in the file.
        split_counts: trajectories in train, validation, test.
        rejected: trajectories the system rejected and that were redrawn.
        failed: trajectories the solver could not finish and that were redrawn.
        n_f_evals: right-hand-side evaluations summed over all trajectories solved
            (redrawn ones included).
        solve_seconds: time spent in the solver.
        seconds: wall time of the whole call.
    """

    path: Path
    trajectories: int
    split_counts: tuple[int, int, int]
    rejected: int
    failed: int
    n_f_evals: int
    solve_seconds: float
    seconds: float


def estimate(config: GenerateConfig) -> SizeEstimate:
    """The size of the file, the memory, the solver steps and the rough time a resolved
    config will take (`mpnode_cli.data.size.generate_estimate`); for a shard, its own
    trajectories'."""
    start, stop = trajectory_range(config)
    return generate_estimate(config, build_system(config), stop - start)


def trajectory_range(config: GenerateConfig) -> tuple[int, int]:
    """`(start, stop)`: the trajectories a resolved config's file holds (all, or a shard's).

    Raises:
        ValueError: more shards than solver chunks.
    """
    if config.shard is None:
        return 0, config.trajectories
    return shard_range(config.trajectories, config.chunk_size, *config.shard)


def output_path(config: GenerateConfig) -> Path:
    """The file a resolved config writes: `out`, or its shard's name beside it."""
    if config.shard is None:
        return Path(config.out)
    return shard_path(config.out, *config.shard)


def resolve_generate_config(config: GenerateConfig, *, dry_run: bool = True) -> GenerateConfig:
    """Fill in every system-dependent default and check the system can be built as asked.

    A job too big for the memory available, or of more fixed steps than `max_steps`, is
    refused before anything is built (`mpnode_cli.data.size.check_job`). With `dry_run`,
    the first graph is built and one initial state drawn, so that a topology that cannot
    exist at this size, or an option that does not fit it, fails here with one clear
    message rather than after minutes of solving.

    Raises:
        ValueError: unknown system, parameter, topology or size; an unreadable edge list;
            a job too large for this machine.
    """
    system = build_system(config)
    if config.grid is not None and not system.grid_layout:
        raise ValueError(
            f"grid {config.grid}: {system.name}'s nodes have no grid layout, so grid means "
            f"nothing for it (systems with one: {', '.join(grid_systems()) or 'none'}); use "
            f"--nodes {config.grid**2} instead")
    fields = config.model_dump()
    if config.system_file is not None:  # stored where the file was found, for provenance
        fields["system_file"] = Path(config.system_file).resolve()
    for key, value in system.data_defaults.items():
        if fields[key] is None:
            fields[key] = value

    if config.edge_list is not None:
        n = read_edges(config.edge_list, directed=config.directed).num_nodes
        asked = config.nodes or (config.grid**2 if config.grid else None)
        if asked not in (None, n):
            raise ValueError(f"{asked} nodes asked for, but the edge list has {n}")
        fields["nodes"], fields["topology"] = n, "edgelist"
    else:
        if config.grid is not None:
            fields["nodes"] = config.grid**2
        elif config.nodes is None:
            fields["nodes"] = system.default_nodes
        fields["topology"] = config.topology or system.default_topology
    if fields["out"] is None:
        fields["out"] = Path("datasets", f"{config.system}-n{fields['nodes']}-{fields['topology']}"
                             f"{hubs_tag(config.hubs, config.hub_multiplicity)}-s{config.seed}.h5")
    resolved = GenerateConfig(**fields)  # re-checks dt against the filled-in t_end
    trajectory_range(resolved)  # a shard spec that fits these trajectories
    check_job(estimate(resolved), "this dataset",
              "lower --trajectories, --t-end, --nodes or --graphs, or raise --dt",
              solver=resolved.solver)
    if resolved.nodes > DENSE_GRAPH_MAX_NODES and not system.sparse:
        raise ValueError(
            f"system '{system.name}' needs its graph as an N×N matrix, which mpnode builds "
            f"for at most {DENSE_GRAPH_MAX_NODES} nodes, not {resolved.nodes}; systems that "
            f"run on edge lists: {', '.join(sparse_systems())}")
    if not dry_run:
        return resolved

    graph = _graph(system, resolved, 0)
    system.sample(graph, 1, np.random.default_rng(0))
    return resolved


def generate(
    config: GenerateConfig, *, overwrite: bool = False, progress: Progress | None = None,
    stage: Callable[[str], None] | None = None,
) -> GenerateSummary:
    """Simulate the dataset `config` describes and write it to `config.out` (a shard: to
    `output_path(config)`).

    Args:
        config: a generate config (resolved here if it is not already).
        overwrite: replace an existing file at the output path.
        progress: called as `progress(done, total)` after each solved chunk, and within a
            chunk as its solve moves (`done` then counts the chunk's fraction solved).
        stage: called with each step as it starts ("building graph 2 of 5", "solving
            trajectories 1–1024 of 2000", "writing the file").

    Returns:
        A `GenerateSummary`.

    Raises:
        ValueError: a config that does not resolve (see `resolve_generate_config`).
        FileExistsError: the output exists and `overwrite` is False (checked before solving).
        ValueError: an output path that cannot be written, or is an input (checked and
            reserved before solving, `mpnode_cli.paths.reserve_output`).
        KeyboardInterrupt: SIGINT (or SIGTERM, under `interrupt_on_signals`); nothing is
            written.
        GenerateError: trajectories that keep failing after `MAX_REDRAW_ROUNDS` redraws.
        OutOfMemory: memory ran out all the same (one line naming the step).
    """
    from mpnode_cli.paths import reserve_output

    start = time.perf_counter()
    # No dry run: step 1 builds the graphs and step 2 draws the initial states before any
    # solve, and building a large graph twice would double the wait.
    config = resolve_generate_config(config, dry_run=False)
    out = output_path(config)
    with reserve_output(out, overwrite=overwrite, inputs=generate_inputs(config)):
        return _generate(config, out, progress, _Stage(stage), start)


def generate_inputs(config: GenerateConfig) -> tuple[Path | None, ...]:
    """The files a generate config reads, which its output may not be."""
    return config.edge_list, config.system_file


class _Stage:
    """The step `generate` is at: told to the caller's `stage` callback as it starts, and
    named if memory runs out in it."""

    def __init__(self, report: Callable[[str], None] | None) -> None:
        self.now, self.report = "starting", report

    def __call__(self, step: str) -> None:
        self.now = step
        if self.report is not None:
            self.report(step)

    def __str__(self) -> str:
        return self.now


def _generate(config: GenerateConfig, out: Path, progress: Progress | None, stage: _Stage,
              start: float) -> GenerateSummary:
    """`generate` once its output is reserved: solve, redraw, write."""
    import torch

    system = build_system(config)
    lo, hi = trajectory_range(config)
    size = generate_estimate(config, system, hi - lo)
    check_disk(size, out, "this dataset")
    with naming_memory(stage, size.memory_bytes, "lower --chunk-size, --trajectories, "
                       "--t-end or --nodes, or raise --dt"):
        graphs, params = _graphs_and_params(system, config, stage)
        stage("drawing the initial states")
        draws = _draw_trajectories(system, config, graphs)
        ts = torch.arange(config.num_steps + 1, dtype=torch.float64) * config.dt  # [T]
        solved = solve_and_redraw(system, config, ts, graphs, params, draws, progress, stage)
        stage("writing the file")
        return _write(system, config, out, ts, graphs, params, draws, solved, start)


def _graphs_and_params(system: CheckedSystem, config: GenerateConfig, stage: _Stage
                       ) -> tuple[Graphs, dict[str, np.ndarray]]:
    """Step 1: the G graphs and each one's parameters (name → `[G, ...]`).

    The graphs are `[G, N, N]` uint8 matrices up to DENSE_GRAPH_MAX_NODES nodes, edge lists
    above (memory O(E), not O(N²)).
    """
    g, built = config.graphs, []
    for i in range(g):
        stage(f"building graph {i + 1} of {g}")
        built.append(_graph(system, config, i))
    graphs = (Graphs.from_adjacency(np.stack(built)) if isinstance(built[0], np.ndarray)
              else Graphs.from_edge_lists(config.nodes, built))
    per_graph = [
        system.graph_params(graphs.graph(i), np.random.default_rng([config.graph_seed, i]))
        for i in range(g)
    ]
    return graphs, {name: np.stack([p[name] for p in per_graph]) for name in per_graph[0]}


def _draw_trajectories(system: CheckedSystem, config: GenerateConfig, graphs: Graphs) -> Draws:
    """Step 2: trajectories in contiguous blocks per graph, sizes differing by at most one,
    and their initial states; a shard keeps its own."""
    total_k, g = config.trajectories, config.graphs
    graph_index = (np.arange(total_k) * g // total_k).astype(np.int32)  # [K]
    rng = np.random.default_rng(config.seed)
    draws = [system.sample(graphs.graph(i), int((graph_index == i).sum()), rng)
             for i in range(g)]
    y0 = np.concatenate([d[0] for d in draws])  # [K, N, D]
    inputs = {name: np.concatenate([d[1][name] for d in draws]) for name in draws[0][1]}
    first_chunks = list(solver_chunks(np.arange(total_k), graph_index, config.chunk_size))
    # A shard keeps its own solver chunks of the whole and redraws from its own generator.
    lo, hi = trajectory_range(config)
    if config.shard is not None:
        first_chunks = first_chunks[shard_chunks(total_k, config.chunk_size, *config.shard)]
        first_chunks = [(chunk - lo, gi) for chunk, gi in first_chunks]
        rng = np.random.default_rng(redraw_seed(config.seed, *config.shard))
        graph_index, y0 = graph_index[lo:hi], y0[lo:hi]  # [K_s], [K_s, N, D]
        inputs = {name: value[lo:hi] for name, value in inputs.items()}
    return Draws(lo, hi, graph_index, y0, inputs, first_chunks, rng)


def _write(system: CheckedSystem, config: GenerateConfig, out: Path, ts: torch.Tensor,
           graphs: Graphs,
           params: dict[str, np.ndarray], draws: Draws, solved: Solved,
           start: float) -> GenerateSummary:
    """Step 5: split by trajectory and write the file; what `generate` did."""
    from mpnode_cli.data.hdf5 import Dataset
    from mpnode_cli.data.hdf5_write import write_dataset

    split = split_trajectories(config.trajectories, config.split, config.seed)[draws.lo:draws.hi]
    sharding = {}
    if config.shard is not None:
        sharding[SHARD_ATTR] = shard_attribute(config.trajectories, config.chunk_size,
                                                config.seed, *config.shard)
    dataset = Dataset(
        system=system.name,
        dt=config.dt,
        state_names=system.state_names,
        control_names=system.control_names,
        periodic_states=tuple(system.periodic_states),
        seed=config.seed,
        # A single file's config has no `shard` field: it reads as it did before shards.
        config=config.model_dump(mode="json", exclude=set() if config.shard else {"shard"}),
        time=ts.numpy(),
        states=solved.states.astype(config.dtype),
        controls=None if solved.controls is None else solved.controls.astype(config.dtype),
        hidden={name: value.astype(config.dtype) for name, value in solved.hidden.items()},
        graphs=graphs,
        graph_index=draws.graph_index,
        split=split,
        params=params,
        scalar_params=system.scalar_params(),
        solver_status=solved.status,
        solver_n_f_evals=solved.n_f_evals.astype(np.int32),
        extra_attrs={"n_rejected": solved.rejected, "n_failed": solved.failed,
                     "recipe": json.dumps(system.recipe(), sort_keys=True), **sharding},
    )
    write_dataset(out, dataset, overwrite=True)  # over the reservation `generate` made
    counts = np.bincount(split, minlength=3)
    return GenerateSummary(
        path=out,
        trajectories=draws.hi - draws.lo,
        split_counts=(int(counts[0]), int(counts[1]), int(counts[2])),
        rejected=solved.rejected,
        failed=solved.failed,
        n_f_evals=solved.total_f_evals,
        solve_seconds=solved.solve_seconds,
        seconds=time.perf_counter() - start,
    )


def build_system(config: GenerateConfig) -> CheckedSystem:
    """The config's system with its parameters and options, as generate calls it (each
    method's result checked, `mpnode_cli.systems.contract`); a system of your own is first
    loaded from `config.system_file` (or found among the installed entry points).

    Raises:
        ValueError: an unknown system, a file that does not load, or a parameter or
            option the system refuses.
    """
    if config.system_file is not None:
        cls = load_system_file(config.system_file)
        if cls.name != config.system:
            raise ValueError(f"--system-file {config.system_file} defines the system "
                             f"'{cls.name}', not '{config.system}'")
    cls = system_class(config.system)
    try:
        return CheckedSystem(cls(**config.params))
    except BaseException as exc:  # a plug-in's own __init__ may raise anything
        raise named(cls, "__init__", exc) from None


def _graph(system: CheckedSystem, config: GenerateConfig, g: int) -> np.ndarray | EdgeList:
    """Graph g, built with seed `graph_seed + g` (or the edge list): uint8 `[N, N]` up to
    `DENSE_GRAPH_MAX_NODES` nodes, an `EdgeList` above."""
    if config.edge_list is not None:
        graph = read_edges(config.edge_list, directed=config.directed)
        return graph.to_dense() if graph.num_nodes <= DENSE_GRAPH_MAX_NODES else graph
    graph = system.graph(config.topology, config.nodes, config.graph_seed + g)
    w = spread_multiplicity(config.hub_multiplicity, config.graphs, g)
    return join_hubs(graph, config.hubs, w) if config.hubs else graph
