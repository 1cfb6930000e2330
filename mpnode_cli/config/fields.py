"""Pydantic models of each verb's configuration: the one source of truth for what a run did.

A config is built from (lowest precedence first) a preset, a TOML/JSON file, and command-line
options; its resolved form (every default filled in) is written next to the artifact it made,
so any dataset or run can be reproduced from its own files.

This module checks what can be checked without knowing the system (types, ranges, `dt` vs
`t_end`, the split). System-dependent defaults and checks (its topologies, node counts,
parameters) are filled in by `mpnode_cli.data.generate.resolve_generate_config`, which
keeps this module free of imports from higher floors.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from pathlib import Path
from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field, field_validator, model_validator

from mpnode_cli.limits import DENSE_GRAPH_MAX_NODES, MULTIPLICITY_MAX, within_float32
from mpnode_cli.memory import MemorySize
from mpnode_cli.solver.options import SolverOptions

# Seeds are stored as HDF5 int64 attributes and fed to numpy and torch generators.
SEED_MAX = 2**63 - 1

# Relative slack when checking that t_end is a whole number of dt steps (0.3 / 0.1 is not
# exactly 3 in binary floating point).
_GRID_TOL = 1e-9
# The most dt steps in a horizon `0, dt, ..., t_end`: float64 holds every whole number up to
# 2⁵³, so beyond it "t_end is a whole number of dt steps" means nothing (and at inf, from a
# dt of 1e-300, nothing can be counted). Smaller horizons that would not fit in memory are
# refused by the memory estimates of generate and simulate, before anything is allocated.
MAX_STEPS = 2**53


def generate_solver() -> SolverOptions:
    """The solver of `mpnode generate`: ground truth at tight tolerances (float64)."""
    return SolverOptions(rtol=1e-8, atol=1e-10)


def train_solver() -> SolverOptions:
    """The solver of training rollouts: the paper's rtol = atol = 1e-4, with the integral
    step-size controller (fewer steps than PI at these tolerances: docs/solver.md), compiled
    for long runs (`mpnode_cli.training.recipe.resolve_compile`)."""
    return SolverOptions(rtol=1e-4, atol=1e-4, controller="i", compile="auto")


def over_defaults(defaults: Callable[[], SolverOptions], value: Any) -> Any:
    """A `solver` table that names only some options: the rest from the verb's defaults
    (not `SolverOptions`' own, which are `solve`'s)."""
    return {**defaults().model_dump(), **value} if isinstance(value, dict) else value


def _split_fractions(cls: type, value: Any) -> Any:
    """Accept the command line's `"0.7,0.15,0.15"` as well as a list of three numbers."""
    parts = value.replace(" ", "").split(",") if isinstance(value, str) else value
    try:
        numbers = tuple(float(p) for p in parts)
    except (TypeError, ValueError):
        numbers = ()
    if len(numbers) != 3:
        raise ValueError(f"expected three fractions like 0.7,0.15,0.15, got {value!r}")
    return numbers


def _valid_split(cls: type, value: tuple[float, float, float]) -> tuple[float, float, float]:
    if any(not 0.0 <= x <= 1.0 for x in value) or not math.isclose(sum(value), 1.0,
                                                                    abs_tol=1e-6):
        shown = ",".join(f"{x:g}" for x in value)
        raise ValueError(f"train,validation,test fractions must lie in [0, 1] and sum to 1, "
                         f"got {shown}")
    return value


def _check_grid(dt: float, t_end: float) -> None:
    """Samples `0, dt, ..., t_end`: t_end must be a whole number of dt steps."""
    if dt > t_end:
        raise ValueError(f"dt ({dt:g}) is larger than t_end ({t_end:g})")
    steps = t_end / dt
    if not steps <= MAX_STEPS:  # also NaN and inf, which `round` cannot take
        raise ValueError(f"t_end / dt is {steps:.3g} steps, more than the 2**53 a horizon may "
                         "hold: lower t_end or raise dt")
    if abs(steps - round(steps)) > _GRID_TOL * max(1.0, steps):
        raise ValueError(f"t_end ({t_end:g}) must be a whole number of dt ({dt:g}) steps")


def _check_graph_source(adjacency: Path | None, edge_list: Path | None, directed: bool) -> None:
    """A user's graph comes as exactly one of an adjacency array or an edge list."""
    if (adjacency is None) == (edge_list is None):
        raise ValueError("give the graph as exactly one of --adjacency A.npy or "
                         "--edge-list E.txt")
    if directed and edge_list is None:
        raise ValueError("directed applies to an edge list only (--edge-list); an "
                         "adjacency matrix says its own direction")


def _names(cls: type, value: Any) -> Any:
    """Accept the command line's `"x,y"` as well as a list of names."""
    return [part.strip() for part in value.split(",")] if isinstance(value, str) else value


# A user's graph, as `import` and `simulate` take it (an adjacency array or an edge list),
# and `generate` an edge list.
_ADJACENCY = ("Graph(s) as .npy: [N, N] for all trajectories or [K, N, N] one each; A_ij = 1 "
              "iff node j sends to node i.")
_EDGE_LIST = ("Graph as a text file of 'i j' lines (optional weight column, 0 or 1), "
              "undirected unless --directed (docs/dataset-format.md).")
_DIRECTED = "Read the edge list's 'i j' as one edge i → j."


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
    directed: bool = Field(False, description=_DIRECTED)
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

    _parse_split = field_validator("split", mode="before")(_split_fractions)
    _check_split = field_validator("split")(_valid_split)

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
            _check_grid(self.dt, self.t_end)
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


class ImportConfig(BaseModel):
    """What `mpnode import` makes: one dataset file (system "custom") from a user's arrays.

    Each field's description is its `mpnode import` option's help
    (`mpnode_cli.cli.importer`; the edge list is read by
    `mpnode_cli.edge_files.read_edge_list`, the split drawn as generate's,
    `numpy.random.default_rng([seed, 1])`).
    """

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)

    states: Path = Field(description=(
        "Trajectories [K, T, N, D]: .npy, .npz (array 'states', optional 'time') or a long "
        "CSV with columns trajectory, time, node and one per state."))
    adjacency: Path | None = Field(None, description=_ADJACENCY)
    edge_list: Path | None = Field(None, description=_EDGE_LIST)
    directed: bool = Field(False, description=_DIRECTED)
    dt: float = Field(gt=0, description=(
        "Sample spacing (a time column or array must step by it)."))
    controls: Path | None = Field(None, description=(
        "Zero-order-hold controls [K, T, N, U] as .npy."))
    state_names: list[str] | None = Field(None, description=(
        "Comma-separated names of the D states (default: the CSV's columns, else x0, x1, "
        "...)."))
    control_names: list[str] | None = Field(None, description=(
        "Comma-separated names of the U controls (default u0, u1, ...)."))
    split: tuple[float, float, float] = Field((0.7, 0.15, 0.15), description=(
        "Train, validation, test fractions by trajectory, summing to 1."))
    seed: int = Field(0, ge=0, le=SEED_MAX, description="Seed of the split.")
    dtype: Literal["float32", "float64"] = Field("float32", description=(
        "Storage dtype of the states and controls."))
    out: Path | None = Field(None, description=(
        "Output file (default datasets/<states>.h5); a path ending in / is refused: name "
        "the file."))
    periodic: list[str] = Field(default_factory=list, description=(
        "A state that is an angle (mod 2π), by name; repeat for more. Recorded as the "
        "dataset's periodic_states (docs/dataset-format.md)."))

    _parse_split = field_validator("split", mode="before")(_split_fractions)
    _check_split = field_validator("split")(_valid_split)
    _parse_names = field_validator("state_names", "control_names", mode="before")(_names)

    @model_validator(mode="after")
    def _check(self) -> ImportConfig:
        _check_graph_source(self.adjacency, self.edge_list, self.directed)
        for field in ("state_names", "control_names"):
            names = getattr(self, field) or []
            if any(not name for name in names) or len(set(names)) != len(names):
                raise ValueError(f"{field} must be distinct, non-empty names, got "
                                 f"{','.join(names)!r}")
        return self


class SimulateConfig(BaseModel):
    """What `mpnode simulate` does: a trained node model rolled out on graphs of your own.

    Each field's description is its `mpnode simulate` option's help
    (`mpnode_cli.cli.simulate`); the graph is given as for `ImportConfig`.
    """

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)

    checkpoint: Path = Field(description=(
        "A checkpoint (.pt), or a run folder (its checkpoints/best.pt)."))
    x0: Path = Field(description=(
        "Initial states [K, N, D] (or [N, D]) in physical units, .npy."))
    adjacency: Path | None = Field(None, description=_ADJACENCY)
    edge_list: Path | None = Field(None, description=_EDGE_LIST)
    directed: bool = Field(False, description=_DIRECTED)
    t_end: float = Field(gt=0, description="Last sample time (samples 0, dt, ..., t_end).")
    dt: float = Field(gt=0, description="Sample spacing.")
    controls: Path | None = Field(None, description=(
        "Controls [K, T, N, U] in physical units (zero-order hold), T = t_end / dt + 1, "
        ".npy."))
    batch_size: int = Field(128, ge=1, description="Trajectories per rollout.")
    device: Literal["cpu", "cuda"] = Field("cpu", description="Where the rollouts run.")
    dtype: Literal["float32", "float64"] = Field("float32", description=(
        "Storage dtype of the predictions."))
    out: Path | None = Field(None, description=(
        "Output file (default predictions/<x0 file name>.h5); a path ending in / is "
        "refused: name the file."))
    member: int | None = Field(None, description=(
        "An ensemble checkpoint's member to roll out alone (none: the members' mean, with "
        "their spread in hidden/ensemble_std)."))

    @model_validator(mode="after")
    def _check(self) -> SimulateConfig:
        _check_graph_source(self.adjacency, self.edge_list, self.directed)
        _check_grid(self.dt, self.t_end)
        return self

    @property
    def num_steps(self) -> int:
        """Number of dt steps, T − 1."""
        return round(self.t_end / self.dt)


class TrainConfig(BaseModel):
    """What `mpnode train` (and `mpnode finetune`) does: one model, its datasets, one run folder.

    Fields not given are filled from the run's recipe (`mpnode_cli.training.recipe`); the
    defaults below equal mpnode's recipe without a system's recommendation. Each field's
    `description` documents it, and is the help of its option in `mpnode train` and
    `mpnode finetune`, which are built from these fields.
    """

    # No inf or NaN in any number (`--t-end inf` would never end).
    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)

    dataset: Path | list[Path] = Field(description=(
        "The training dataset (an mpnode .h5 file): its train split is fitted, its "
        "validation split selects the best epoch, its test split is reported. Or a list of "
        "datasets of one system and per-node sizes (N, graphs and the number of samples "
        "may differ), trained on at once: their splits are pooled (mpnode_cli.data.pooled). "
        "A list of one is stored as that one path, so a one-file config reads as it always "
        "has; `datasets` gives the list either way."))
    model: str = Field("mpnode", description="The model, by its registry name.")
    model_options: dict[str, Any] = Field(default_factory=dict, description=(
        "Options of that model, by name (a [model_options] table in a TOML file); each "
        "model declares its own, with their defaults, in mpnode_cli.models.options. Options "
        "left out take the model's defaults; the training layer validates them against the "
        "model (mpnode_cli.training.recipe.resolve_train_config), and the resolved config written "
        "to a run holds every option of the model that was built."))
    recipe: Literal["mpnode", "paper"] = Field("mpnode", description=(
        "Where the fields left out come from: mpnode (measured choices and the dataset "
        "system's recommendation) or paper (the paper's exact choices)."))
    loss: Literal["huber", "mse", "node-mse"] = Field("mse", description=(
        "Training loss: mse; huber (δ = 1, summed over time and features, mean over "
        "trajectories × nodes: the authors' Huber along time); or node-mse, each node's "
        "squared error over its own variance in the window, for graphs whose hubs' states "
        "dwarf a typical node's."))
    lr: float = Field(1e-3, gt=0, description="Adam learning rate.")
    min_lr: float = Field(1e-6, ge=0, description=(
        "Lowest lr: schedules stop there, and a rollback below it ends the run as "
        "diverged."))
    schedule: Literal["plateau", "cosine", "constant"] = Field("plateau", description=(
        "lr schedule: plateau (halve it after `patience` epochs without validation gain), "
        "cosine (down to min_lr over the epochs) or constant."))
    batch_size: int = Field(32, ge=1, description="Trajectories per step.")
    even_batches: bool = Field(True, description=(
        "Batches of nearly equal size each epoch (no tiny last one), or full ones and a "
        "partial last one."))
    val_batch_size: int = Field(1024, ge=1, description=(
        "Trajectories per validation rollout."))
    clip: float = Field(500.0, gt=0, description="Global gradient-norm clip.")
    patience: int = Field(50, ge=1, description=(
        "Plateau schedule: epochs without validation gain before the lr halves."))
    wrap_angles: bool = Field(False, description=(
        "Take the training loss and every error (validation, evaluate, zeroshot, the "
        "baselines) of the states the dataset declares periodic mod 2π, as the wrapped "
        "difference atan2(sin Δ, cos Δ): for angles defined only mod 2π, such as "
        "Kuramoto's phases, where a whole turn is no error. Off: plain differences, as "
        "runs made without this option report."))
    balance_datasets: bool = Field(False, description=(
        "Several datasets: weigh each one's loss (training, and the validation that picks "
        "the best epoch) by 1 / its normalized states' variance; off: all values alike."))
    noise: float = Field(1e-4, ge=0, description=(
        "Std of Gaussian noise on the normalized training states (inputs and targets "
        "alike), fresh every batch."))
    epochs: int = Field(4000, ge=1, description=(
        "The last epoch to train (on resume the total, not the extra)."))
    seed: int = Field(0, ge=0, le=SEED_MAX, description=(
        "Seed of initialization, shuffling and noise."))
    seeds: int = Field(1, ge=1, le=64, description=(
        "Members of an ensemble, trained at once as one batched model: member k has seed "
        "seed + k (its own initialization, batch order and noise), its own lr schedule, "
        "clipping, best epoch and early stop, and all of them are integrated in one solve. "
        "The checkpoints hold every member; evaluate, zeroshot and compare report mean ± std "
        "over them, and simulate writes their spread."))
    time_limit: float | None = Field(None, gt=0, description=(
        "Stop after the epoch in which the run's time (the sum of its epochs, validation "
        "included; a resumed run's earlier epochs count) reaches this many seconds: a "
        "budget of wall time rather than epochs (none: train every epoch)."))
    stop_patience: int | None = Field(None, ge=1, description=(
        "Early stop: a member stops training after this many epochs without a better "
        "validation loss, and the run stops when all have (none: train every epoch)."))
    device: Literal["cpu", "cuda"] = Field("cpu", description="Where to train.")
    dtype: Literal["float32", "float64"] = Field("float32", description=(
        "Precision of the weights and the training rollouts; float64 is slower, for "
        "checks that compare runs to round-off and for stiff systems."))
    memory_budget: MemorySize | None = Field(None, description=(
        "Memory the run may take, e.g. 4GiB or 500MiB (default: what is free): past it, "
        "steps backpropagate through checkpointed solves (docs/training-recipe.md)."))
    run_dir: Path | None = Field(None, description=(
        "The run folder (default runs/<dataset>-<model>-<time>)."))
    solver: SolverOptions = Field(default_factory=train_solver, description=(
        "How the rollouts are integrated, in training and in every evaluation of the "
        "checkpoints; default adaptive Tsit5 at rtol = atol = 1e-4 (train_solver). A table "
        "that names only some options takes the others from that default."))
    horizon_curriculum: bool = Field(False, description=(
        "Train on prefixes of the trajectories growing from curriculum_start samples to "
        "the whole horizon over curriculum_epochs epochs (validation takes it whole)."))
    curriculum_start: int = Field(5, ge=2, description=(
        "Curriculum: samples per trajectory in the first epoch."))
    curriculum_epochs: int = Field(100, ge=1, description=(
        "Curriculum: epochs to reach the whole horizon."))
    max_bad_steps: int = Field(5, ge=1, description=(
        "Skipped batches in a row (non-finite loss or gradient, failed solves) before the "
        "last epoch's state is restored at half the lr."))
    plots: bool = Field(True, description=(
        "Draw the test-split plots into the run folder at the end."))
    init_checkpoint: Path | None = Field(None, description=(
        "Finetune: start from this checkpoint's weights and architecture (model and "
        "model_options are then ignored), with a fresh optimizer."))
    trajectories: int | None = Field(None, ge=1, description=(
        "Use only the first K train trajectories of each dataset (all of them, with a "
        "warning, where a dataset has fewer)."))
    renormalize: bool = Field(False, description=(
        "Finetune: fit the normalization on the new train split instead of reusing the "
        "checkpoint's; better when the new graphs' states have another scale "
        "(docs/cli.md)."))
    allow_other_system: bool = Field(False, description=(
        "Finetune: accept a dataset whose system differs from the checkpoint's (refused "
        "by default: the model learned another system)."))
    allow_predictions: bool = Field(False, description=(
        "Accept a model's predictions (evaluate --save-predictions, simulate) as training "
        "data; refused by default, as a model would learn another model's errors."))
    stream: bool = Field(False, description=(
        "Read the batches from the dataset file as they are needed (a thread reads two "
        "ahead), for data larger than memory; the losses are those of the data in "
        "memory."))
    for_graphs: list[Path] = Field(default_factory=list, description=(
        "Train for deployment to these graphs (mpnode datasets, adjacency .npy or edge "
        "lists; only their graphs are read): degree-coverage data reaching their largest "
        "in-degree are simulated into the run folder and trained on beside the datasets, "
        "with the transfer recipe (docs/transfer.md)."))
    for_in_degree: int | None = Field(None, ge=1, description=(
        "As --for-graphs, for nodes of in-degree up to this."))
    system_file: Path | None = Field(None, description=(
        "With --for-graphs: the plug-in system's file, where the dataset's has moved."))
    coverage: dict[str, Any] | None = Field(None, description=(
        "Set by the run: the coverage data --for-graphs made (file, W, seeds, reach)."))

    # They meet float32 tensors (the optimizer's, the gradients', the states').
    _in_float32 = field_validator("lr", "min_lr", "clip", "noise")(within_float32)

    @field_validator("solver", mode="before")
    @classmethod
    def _fill_solver(cls, value: Any) -> Any:
        return over_defaults(train_solver, value)

    @field_validator("dataset")
    @classmethod
    def _one_or_several(cls, value: Path | list[Path]) -> Path | list[Path]:
        if isinstance(value, list) and not value:
            raise ValueError("give at least one dataset")
        return value[0] if isinstance(value, list) and len(value) == 1 else value

    @model_validator(mode="after")
    def _check_members(self) -> TrainConfig:
        if self.seeds > 1 and self.seed + self.seeds - 1 > SEED_MAX:
            raise ValueError(f"seeds: the members' seeds seed … seed + {self.seeds - 1} "
                             f"pass {SEED_MAX}; give a smaller seed")
        if self.seeds > 1 and isinstance(self.dataset, list):
            # Each member draws its own batch order, and with several datasets a step
            # would hold batches of different graph sizes, which one solve cannot stack.
            raise ValueError("seeds: an ensemble trains on one dataset; train one run per "
                             "seed on several datasets, or give one dataset")
        self.solver.check_precision(self.dtype)
        return self

    @property
    def datasets(self) -> list[Path]:
        """The training datasets, in the order given (one or several)."""
        return list(self.dataset) if isinstance(self.dataset, list) else [self.dataset]
