"""The config of `mpnode generate`."""

from __future__ import annotations

from pathlib import Path
from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field, field_validator, model_validator

from mpnode_cli.config.fields import (
    DIRECTED_HELP,
    SEED_MAX,
    check_grid,
    generate_solver,
    over_defaults,
    split_fractions,
    valid_split,
)
from mpnode_cli.limits import DENSE_GRAPH_MAX_NODES, MULTIPLICITY_MAX
from mpnode_cli.solver.options import SolverOptions


class GenerateConfig(BaseModel):
    """What `mpnode generate` makes: one system on G graphs, K trajectories, one HDF5 file.

    Fields left `None` take the system's defaults in `resolve_generate_config`. Each field's
    description is its `mpnode generate` option's help (`mpnode_cli.cli.generate`).
    """

    # No inf or NaN in any number (`--t-end inf` would never end).
    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)

    system: str = Field(description=(
        "Registry name (`mpnode_cli.systems.registry.SYSTEMS`) or a system of your own."))
    system_file: Path | None = Field(None, description=(
        "A Python file defining your own System subclass (docs/custom-systems.md); its "
        "options go in as -p NAME=VALUE."))
    params: dict[str, float | str] = Field(default_factory=dict, description=(
        "Scalar parameters and options of the system, e.g. K for kuramoto."))
    nodes: int | None = Field(None, ge=1, description="Number of nodes N.")
    grid: int | None = Field(None, ge=1, description="Square grid side: N = grid².")
    topology: str | None = Field(None, description="One of the system's topologies.")
    graphs: int = Field(1, ge=1, description="Distinct graphs G; trajectories spread evenly.")
    graph_seed: int = Field(0, ge=0, le=SEED_MAX, description=(
        "Graph g is built with seed graph-seed + g; per-graph parameters (lorenz coupling, "
        "kuramoto ω) come from the same seeds, so datasets that share a graph seed share "
        "their systems whatever their trajectory seed."))
    edge_list: Path | None = Field(None, description=(
        "Your own graph: text file of 'i j' lines, undirected unless --directed "
        "(docs/dataset-format.md)."))
    hubs: int = Field(0, ge=0, description=(
        "Degree coverage: join the H highest-degree nodes of every graph to all others, so "
        "in-degrees reach N − 1 (docs/transfer.md)."))
    hub_multiplicity: int = Field(1, ge=1, le=MULTIPLICITY_MAX, description=(
        "Join the hubs by parallel edges, 1 to W of them spread evenly over the graphs, so "
        "hubs reach in-degree W·(N − 1) on N ≤ 256 nodes (a multigraph; docs/transfer.md)."))
    directed: bool = Field(False, description=DIRECTED_HELP)
    trajectories: int | None = Field(None, ge=1, description="Number of trajectories K.")
    t_end: float | None = Field(None, gt=0, description=(
        "Last sample time (samples 0, dt, ..., t_end)."))
    dt: float | None = Field(None, gt=0, description="Sample spacing.")
    seed: int = Field(0, ge=0, le=SEED_MAX, description=(
        "Seed of the initial states and of the train/validation/test split."))
    split: tuple[float, float, float] = Field((0.7, 0.15, 0.15), description=(
        "Train, validation, test fractions by trajectory, summing to 1."))
    solver: SolverOptions = Field(default_factory=generate_solver, description=(
        "How the trajectories are integrated (float64 throughout); default Tsit5 at rtol "
        "1e-8, atol 1e-10 (generate_solver). A table that names only some options takes "
        "the others from that default."))
    dtype: Literal["float32", "float64"] = Field("float32", description=(
        "Storage dtype of the states."))
    out: Path | None = Field(None, description=(
        "Output file (default datasets/<system>-n<N>-<topology>-s<seed>.h5); with --shard, "
        "the name its shards are named after. A path ending in / is refused: name the "
        "file."))
    chunk_size: int = Field(1024, ge=1, description=(
        "Trajectories per solver batch (bounds memory)."))
    shard: tuple[int, int] | None = Field(None, description=(
        "Write only shard i of n (0 ≤ i < n) to <out stem>.shard-000i-of-000n.h5, for n "
        "processes or machines; mpnode merge joins the n files into the one file generate "
        "would write. Shards hold whole solver chunks (n ≤ trajectories / chunk-size)."))

    _parse_split = field_validator("split", mode="before")(split_fractions)
    _check_split = field_validator("split")(valid_split)

    @field_validator("solver", mode="before")
    @classmethod
    def _fill_solver(cls, value: Any) -> Any:
        return over_defaults(generate_solver, value)

    @field_validator("shard", mode="before")
    @classmethod
    def _parse_shard(cls, value: Any) -> Any:
        """`"i/n"` (the command line's) or `[i, n]`, with 0 ≤ i < n."""
        if value is None:
            return None
        parts = value.split("/") if isinstance(value, str) else value
        try:
            index, count = (int(str(p).strip()) for p in parts)
        except (TypeError, ValueError):
            index, count = -1, 0
        if not 0 <= index < count:
            raise ValueError(f"expected i/n with 0 ≤ i < n, e.g. 0/4 for the first of four "
                             f"shards, got {value!r}")
        return index, count

    @model_validator(mode="after")
    def _check_cross_fields(self) -> GenerateConfig:
        if self.dt is not None and self.t_end is not None:
            check_grid(self.dt, self.t_end)
        if self.nodes is not None and self.grid is not None and self.nodes != self.grid**2:
            raise ValueError(f"nodes ({self.nodes}) and grid ({self.grid}) disagree: a grid of "
                             f"side {self.grid} has {self.grid**2} nodes; give only one of them")
        if self.directed and self.edge_list is None:
            raise ValueError("directed applies to an edge list only (--edge-list)")
        if self.edge_list is not None and self.topology not in (None, "edgelist"):
            raise ValueError(f"give either a topology ({self.topology}) or an edge list, not both")
        if self.edge_list is not None and self.hubs:
            raise ValueError("hubs joins nodes of generated graphs; an edge list is used as "
                             "it is (add the edges to the file instead)")
        if self.nodes is not None and self.hubs > self.nodes:
            raise ValueError(f"hubs ({self.hubs}) must be at most nodes ({self.nodes})")
        if self.hub_multiplicity > 1 and not self.hubs:
            raise ValueError("hub multiplicity sets the edges that join the hubs; give "
                             "hubs too (--hubs H)")
        if (self.hub_multiplicity > 1 and self.nodes is not None
                and self.nodes > DENSE_GRAPH_MAX_NODES):
            raise ValueError(f"hub multiplicity needs graphs of at most "
                             f"{DENSE_GRAPH_MAX_NODES} nodes (held as matrices), not "
                             f"{self.nodes}")
        if self.trajectories is not None and self.trajectories < self.graphs:
            raise ValueError(f"trajectories ({self.trajectories}) must be at least graphs "
                             f"({self.graphs}) so that every graph has a trajectory")
        self.solver.check_precision("float64")  # generate integrates in float64
        return self

    @property
    def num_steps(self) -> int:
        """Number of dt steps, T − 1 (after resolution)."""
        if self.t_end is None or self.dt is None:
            raise ValueError("num_steps needs a resolved config (t_end and dt set)")
        return round(self.t_end / self.dt)
