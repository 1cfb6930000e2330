"""Degree coverage for `mpnode train --for-graphs`: the data a node model needs to hold on
the hubs of the graphs it will be deployed to.

A node model meets, on a larger graph, hubs with more neighbours than any node of its
training graphs, and a node network has to guess there (Laber, Eliassi-Rad & Klein,
arXiv:2602.08980, 2026). In every system of the form ẋ_i = f(x_i) + Σ_j A_ij g(x_i, x_j) a
node's coupling is a sum over its edges, so a hub that hears each of its N − 1 neighbours
w times has the neighbour sum, and so the state, of a hub of in-degree w·(N − 1). The
coverage dataset is the source dataset's system, parameters, sizes and solver, simulated
again on graphs whose `COVERAGE_HUBS` hubs are joined to every other node by parallel
edges, 1 to W of them spread over the graphs (`mpnode generate --hubs --hub-multiplicity`),
with W the least that reaches the targets' largest in-degree. Only the targets' graphs are
read, never their trajectories (docs/transfer.md, "Degree coverage").

The run trains on the source and the coverage data at once, with the transfer recipe
(`mpnode_cli.training.recipe`), and its config records what was made (`coverage`).
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from mpnode_cli.config.generate import GenerateConfig
from mpnode_cli.config.train import TrainConfig
from mpnode_cli.limits import MULTIPLICITY_MAX

if TYPE_CHECKING:
    from mpnode_cli.training.run_folder import RunFolder

COVERAGE_HUBS = 2  # hubs per coverage graph
COVERAGE_SEED = 500  # the coverage data's data (and graph) seeds are the source's + this
COVERAGE_FILE = "coverage.h5"  # in the run folder


def in_degrees(path: str | Path) -> np.ndarray:
    """int64: the in-degree of every node of every graph in a target, an edge of
    multiplicity w counted w times.

    A target is an mpnode dataset (`.h5`; its graphs only are read), an adjacency `.npy`
    (`[N, N]` or `[K, N, N]`, A[i, j] = 1 iff j sends to i) or an edge list (any other
    file, read as `mpnode simulate --edge-list` reads it: undirected).

    Raises:
        ValueError, FileNotFoundError: a file that is none of these (one line).
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"target graph {path} does not exist")
    if path.suffix.lower() in (".h5", ".hdf5"):
        from mpnode_cli.data.hdf5 import read_header

        return read_header(path)["graphs"].in_degree().reshape(-1)
    if path.suffix.lower() == ".npy":
        try:
            a = np.load(path, allow_pickle=False)
        except (OSError, ValueError) as exc:
            raise ValueError(f"{path}: not a readable .npy adjacency ({exc})") from None
        if a.ndim not in (2, 3) or a.shape[-1] != a.shape[-2] or not np.isfinite(a).all():
            raise ValueError(f"{path}: an adjacency must be [N, N] or [K, N, N] of finite "
                             f"numbers, got shape {list(a.shape)}")
        return np.rint(a.reshape(-1, a.shape[-1], a.shape[-1]).sum(axis=-1)).astype(
            np.int64).reshape(-1)
    from mpnode_cli.graphs.edge_files import read_edges

    edges = read_edges(path)
    return np.bincount(edges.receivers, minlength=edges.num_nodes)


def targets_max_in_degree(paths: list[Path]) -> int:
    """The largest in-degree over every target (`in_degrees`)."""
    return max(int(in_degrees(p).max(initial=0)) for p in paths)


def multiplicity_for(max_in_degree: int, nodes: int) -> int:
    """W, the least number of parallel edges per hub link with W·(N − 1) ≥ `max_in_degree`
    (at least 1).

    Raises:
        ValueError: no W up to `MULTIPLICITY_MAX` reaches it on graphs of `nodes` nodes.
    """
    if nodes < 2:
        raise ValueError("degree coverage needs graphs of at least 2 nodes")
    w = max(1, math.ceil(max_in_degree / (nodes - 1)))
    if w > MULTIPLICITY_MAX:
        raise ValueError(
            f"in-degree {max_in_degree} needs hubs joined {w} times to each of the "
            f"source's {nodes - 1} other nodes, above the {MULTIPLICITY_MAX} a dataset "
            "holds: train on larger source graphs")
    return w


def coverage_config(source: Path, max_in_degree: int, out: Path,
                    system_file: Path | None = None) -> GenerateConfig:
    """The generate config of the coverage data for the dataset at `source`: its own
    resolved config with `COVERAGE_HUBS` hubs, W from `max_in_degree`, half its
    trajectories (at least one per graph) and seeds offset by `COVERAGE_SEED`. A system
    that draws parameters per graph (Kuramoto's natural frequencies) keeps the source's
    graph seeds, so that the coverage graphs carry the same parameters.

    Raises:
        ValueError: the source cannot be simulated again (imported data, an edge list of
            the user's, a plug-in whose file is gone), in one line naming what to do.
    """
    from mpnode_cli.data.hdf5 import read_header

    header = read_header(source)
    stored, system = header["attrs"]["config"], header["attrs"]["system"]
    try:
        config = GenerateConfig(**stored)
    except (TypeError, ValueError):
        raise ValueError(
            f"--for-graphs: {source} holds imported data (system '{system}'), not data "
            "mpnode generate made, so there is no simulator to make coverage data with: train on "
            f"data whose graphs reach in-degree {max_in_degree}, or make such data with a "
            "system file of your own (mpnode generate --system-file FILE --hubs 2 "
            "--hub-multiplicity W)") from None
    if config.edge_list is not None:
        raise ValueError(f"--for-graphs: {source} was generated on an edge list of yours, "
                         "whose hubs mpnode does not rewire: add hub edges to a copy of it "
                         "and generate coverage data from that")
    plugin = system_file or config.system_file
    if plugin is not None and not Path(plugin).is_file():
        raise ValueError(f"--for-graphs: {source}'s system '{system}' comes from "
                         f"{plugin}, which is not there now: give --system-file FILE")
    w = multiplicity_for(max_in_degree, int(config.nodes or header["graphs"].num_nodes))
    per_graph = any(name.startswith("params/") for name in header["shapes"])
    return config.model_copy(update={
        "hubs": min(COVERAGE_HUBS, int(config.nodes)), "hub_multiplicity": w,
        "trajectories": max(int(config.trajectories) // 2, config.graphs),
        "seed": config.seed + COVERAGE_SEED, "out": out, "shard": None,
        "system_file": plugin,
        "graph_seed": config.graph_seed + (0 if per_graph else COVERAGE_SEED)})


def check_request(config: TrainConfig) -> None:
    """Refuse what `--for-graphs` cannot do, before any work (one line)."""
    if config.seeds > 1:
        raise ValueError("--for-graphs trains on the source and its coverage data at once, "
                         "and an ensemble trains on one dataset: train one run per --seed")
    if config.init_checkpoint is not None:
        raise ValueError("--for-graphs makes a new run's data; finetune on coverage data "
                         "made with mpnode generate --hubs 2 --hub-multiplicity W instead")


def prepare(config: TrainConfig, folder: RunFolder, emit: Any) -> TrainConfig:
    """Make the coverage data of a new `--for-graphs` run in its run folder, reserved here,
    and return the config that trains on the source and it, with the `coverage` record.

    A failure or an interrupt leaves no folder behind (`RunFolder`).

    Raises:
        ValueError, FileNotFoundError: what `coverage_config` and `in_degrees` refuse.
        KeyboardInterrupt: Ctrl-C or SIGTERM while generating.
    """
    from mpnode_cli.data.generate import generate, resolve_generate_config
    from mpnode_cli.training import run as runs

    check_request(config)
    targets = [Path(p) for p in config.for_graphs]
    reach = max(targets_max_in_degree(targets) if targets else 0, config.for_in_degree or 0)
    run_dir = Path(config.run_dir or runs.default_run_dir(config.datasets, config.model))
    source = Path(config.datasets[0])
    plan = resolve_generate_config(
        coverage_config(source, reach, run_dir.resolve() / COVERAGE_FILE, config.system_file))
    runs.check_new(run_dir)
    folder.reserve(run_dir)
    emit({"event": "coverage", "reach": reach, "multiplicity": plan.hub_multiplicity,
          "hubs": plan.hubs, "trajectories": plan.trajectories, "nodes": plan.nodes,
          "path": str(plan.out)})
    generate(plan)
    record = {"targets": [str(p.resolve()) for p in targets],
              "for_in_degree": config.for_in_degree, "max_in_degree": reach,
              "hubs": plan.hubs, "multiplicity": plan.hub_multiplicity,
              "hub_in_degree": plan.hub_multiplicity * (plan.nodes - 1),
              "trajectories": plan.trajectories, "seed": plan.seed,
              "graph_seed": plan.graph_seed, "dataset": COVERAGE_FILE}
    return config.model_copy(update={"dataset": [*config.datasets, Path(plan.out)],
                                     "run_dir": run_dir, "coverage": record})
