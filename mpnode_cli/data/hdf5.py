"""Dataset files, format "mpnode-dataset" version 3: the format and its reader (reads 1 and
2); `mpnode_cli.data.hdf5_write` writes it.

The layout is documented field by field in `docs/dataset-format.md`. In short: root
attributes describe the system and carry the resolved generate config; `states [K, T, N, D]`
holds the trajectories (one HDF5 chunk per trajectory); the graphs are edge lists,
`graph/edges [2, E]` (senders, receivers) with `graph/num_edges [G]`, plus the matrices
`graph/adjacency [G, N, N]` for graphs of at most `DENSE_GRAPH_MAX_NODES` nodes, and
`graph_index [K]` says which graph each trajectory ran on; `params/` holds the system's
parameters; `split [K]` assigns trajectories to train/validation/test. Version 1 stored
only `graph/adjacency`; its edge lists are derived when it is read. Version 3 added the
root attribute `periodic_states` (JSON list of the state names that are angles, mod 2π);
a version 1 or 2 file reads with none (the attribute's default, `OPTIONAL_ATTRS`).

Writes (`hdf5_write`) are atomic: the file is written under a temporary name in the target
folder and renamed when complete, so an interrupted run (Ctrl-C included) leaves nothing at
the target.
"""

from __future__ import annotations

import json
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import h5py
import numpy as np

from mpnode_cli.config.upgrade import upgrade_solver_fields
from mpnode_cli.data.integrity import (
    CHECKSUM_ATTR,
    HDF5_ERRORS,
    name_damage,
    preflight,
)
from mpnode_cli.data.virtual import virtual_source_problems
from mpnode_cli.graphs.matrices import DENSE_GRAPH_MAX_NODES, EdgeList, Graphs

FORMAT = "mpnode-dataset"
FORMAT_VERSION = 4  # the newest this mpnode reads; files without multigraphs are written as 3
PLAIN_GRAPHS_VERSION = 3
SPLIT_NAMES: tuple[str, ...] = ("train", "validation", "test")

# Root attributes every file must have, and those a file may leave out (with the value a
# reader then assumes): provenance that `mpnode generate` records, and the controls of a
# system that has none. Any others a writer adds land in `Dataset.extra_attrs`.
REQUIRED_ATTRS: tuple[str, ...] = (
    "format", "format_version", "system", "num_nodes", "node_dim", "dt", "state_names")
OPTIONAL_ATTRS: dict[str, Any] = {
    "control_dim": 0, "control_names": "[]", "seed": None, "config": "{}",
    "mpnode_version": None, "created_utc": None, "periodic_states": "[]"}
ROOT_ATTRS = frozenset(REQUIRED_ATTRS) | frozenset(OPTIONAL_ATTRS) | {CHECKSUM_ATTR}
# Values per block when trajectories are read or written a block at a time (64 MB of
# float64): a file larger than memory passes through in pieces.
BLOCK_VALUES = 8 * 2**20


class DatasetFormatError(ValueError):
    """A file that is not an mpnode dataset this version of mpnode can read."""


class NodeSizes:
    """N and D read off `states [K, T, N, D]` (a numpy array or a tensor): what `Dataset`
    and `mpnode_cli.data.dataset.TrajectoryData` share."""

    states: Any

    @property
    def num_nodes(self) -> int:
        """N."""
        return self.states.shape[2]

    @property
    def node_dim(self) -> int:
        """D."""
        return self.states.shape[3]


@dataclass(frozen=True)
class Dataset(NodeSizes):
    """One dataset file in memory (numpy arrays).

    Attributes:
        system: the system's registry name.
        dt: sample spacing.
        state_names: `[D]` names of a node's state components.
        control_names: `[U]` names of a node's control components (empty if none).
        periodic_states: the names among `state_names` that are angles (mod 2π), in state
            order; empty for none (and for every file before format version 3).
        seed: seed of the initial states and split (None when the file does not say).
        config: the resolved generate config (JSON-compatible dict; empty when the file
            holds none, e.g. data that mpnode did not generate).
        time: float64 `[T]`.
        states: `[K, T, N, D]` (float32 or float64): a numpy array, or an array-like
            that reads a block of trajectories as `states[a:b]` (`mpnode import` passes
            a memory-mapped input cast block by block); the writer reads it so.
        graphs: the G graphs (`mpnode_cli.graphs.Graphs`: edge lists, and the `[G, N, N]`
            matrices, `A[g, i, j] = 1` iff node j sends to node i, only for N ≤
            `DENSE_GRAPH_MAX_NODES`).
        graph_index: int32 `[K]`, the graph of each trajectory.
        split: uint8 `[K]`, 0 train, 1 validation, 2 test.
        params: per-graph parameters, each with a leading `[G]` axis.
        scalar_params: the system's scalar parameters by ASCII name.
        solver_status: int8 `[K]`, `mpnode_cli.solver.Status` of each trajectory.
        solver_n_f_evals: int32 `[K]`, right-hand-side evaluations of each trajectory.
        controls: `[K, T, N, U]` zero-order-hold controls, or None when U = 0.
        hidden: unobserved states besides the nodes, each `[K, T, ...]`.
        extrapolation: uint8 `[K, N]` per-node flags of a prediction file (`mpnode
            simulate`): bit 0 a predicted state outside the training range, bit 1 an
            in-degree outside it
            (`mpnode_cli.training.extrapolation_nodes.NodeExtrapolation.flags`); None (not
            written) otherwise.
        extra_attrs: further root attributes (e.g. `n_rejected`, `n_failed`).
        mpnode_version, created_utc: filled in by the writer when None.
    """

    system: str
    dt: float
    state_names: tuple[str, ...]
    control_names: tuple[str, ...]
    seed: int | None
    config: dict[str, Any]
    time: np.ndarray
    states: np.ndarray
    graphs: Graphs
    graph_index: np.ndarray
    split: np.ndarray
    params: dict[str, np.ndarray] = field(default_factory=dict)
    scalar_params: dict[str, float] = field(default_factory=dict)
    solver_status: np.ndarray | None = None
    solver_n_f_evals: np.ndarray | None = None
    controls: np.ndarray | None = None
    hidden: dict[str, np.ndarray] = field(default_factory=dict)
    extrapolation: np.ndarray | None = None
    extra_attrs: dict[str, Any] = field(default_factory=dict)
    mpnode_version: str | None = None
    created_utc: str | None = None
    periodic_states: tuple[str, ...] = ()

    @property
    def num_trajectories(self) -> int:
        """K."""
        return self.states.shape[0]

    @property
    def control_dim(self) -> int:
        """U (0 for autonomous systems)."""
        return len(self.control_names)

    @property
    def num_graphs(self) -> int:
        """G."""
        return len(self.graphs)

    @property
    def adjacency(self) -> np.ndarray:
        """`[G, N, N]` the graphs' matrices, for graphs of at most `DENSE_GRAPH_MAX_NODES`
        nodes (larger ones are only edge lists: `graphs`).

        Raises:
            ValueError: N > `DENSE_GRAPH_MAX_NODES`.
        """
        return self.graphs.dense()


def read_graphs(f: h5py.File) -> Graphs:
    """The graphs of an open dataset file, without an N×N matrix above
    `DENSE_GRAPH_MAX_NODES` nodes.

    Version 2: the edge lists (each graph's put in canonical order), with the stored
    matrices kept for small N. Version 1: the matrices, from which the edge lists are
    derived graph by graph (so a large version-1 graph is in memory one at a time).

    Raises:
        KeyError: neither `graph/edges` nor `graph/adjacency` in the file.
        ValueError: edges that do not fit `num_nodes` or `graph/num_edges`.
    """
    n = int(f["states"].shape[2])
    if "graph/edges" in f:
        edges = f["graph/edges"][()].astype(np.int64).reshape(2, -1)
        graphs = Graphs.from_concatenated(n, edges[0], edges[1], f["graph/num_edges"][()])
        if graphs.dense_ok and "graph/adjacency" in f:
            return Graphs(n, graphs.senders, graphs.receivers, graphs.num_edges,
                          f["graph/adjacency"][()])
        return graphs
    adjacency = f["graph/adjacency"]
    if n <= DENSE_GRAPH_MAX_NODES:
        return Graphs.from_adjacency(adjacency[()])
    return Graphs.from_edge_lists(n, [EdgeList.from_adjacency(adjacency[g])
                                      for g in range(adjacency.shape[0])])


def read_dataset(path: str | Path) -> Dataset:
    """Read a whole dataset file into memory.

    Raises:
        DatasetFormatError: not an mpnode dataset, or a newer format version.
        FileNotFoundError: no such file.
    """
    with open_dataset(path) as f:
        attrs = _root_attrs(f)
        has_controls = "controls" in f
        return Dataset(
            system=attrs["system"],
            dt=attrs["dt"],
            state_names=tuple(json.loads(attrs["state_names"])),
            control_names=tuple(json.loads(attrs["control_names"])),
            seed=attrs["seed"],
            config=_config(attrs["config"]),
            time=f["time"][()],
            states=f["states"][()],
            graphs=read_graphs(f),
            graph_index=f["graph_index"][()],
            split=f["split"][()],
            params={name: value[()] for name, value in _group(f, "params").items()},
            scalar_params=_scalar_params(f),
            solver_status=f["solver/status"][()] if "solver/status" in f else None,
            solver_n_f_evals=f["solver/n_f_evals"][()] if "solver/n_f_evals" in f else None,
            controls=f["controls"][()] if has_controls else None,
            hidden={name: v[()] for name, v in f["hidden"].items()} if "hidden" in f else {},
            extrapolation=f["extrapolation"][()] if "extrapolation" in f else None,
            extra_attrs={key: v for key, v in attrs.items() if key not in ROOT_ATTRS},
            mpnode_version=attrs["mpnode_version"],
            created_utc=attrs["created_utc"],
            periodic_states=tuple(json.loads(attrs["periodic_states"])),
        )


def read_header(path: str | Path) -> dict[str, Any]:
    """A dataset's root attributes and every array's shape and dtype, without the data.

    Returns:
        `{"attrs": {...}, "shapes": {name: (shape, dtype str)}, "split": [K] uint8,
        "solver_status": [K] int8, "graphs": `Graphs`, "scalar_params": {...}}`; the
        JSON attributes (`config`, `state_names`, `control_names`) are decoded.

    Raises:
        DatasetFormatError, FileNotFoundError: as `read_dataset`.
    """
    with open_dataset(path) as f:
        attrs = _root_attrs(f)
        for key in ("state_names", "control_names", "periodic_states"):
            attrs[key] = json.loads(attrs[key])
        attrs["config"] = _config(attrs["config"])
        shapes: dict[str, tuple[tuple[int, ...], str]] = {}

        def shape(name: str, _: Any) -> None:  # by every link: a soft link reads as its target
            if isinstance(obj := f.get(name), h5py.Dataset):
                shapes[name] = (obj.shape, str(obj.dtype))

        f.visititems_links(shape)
        k = f["states"].shape[0]
        return {
            "attrs": attrs,
            "shapes": shapes,
            "split": f["split"][()],
            "solver_status": (f["solver/status"][()] if "solver/status" in f
                              else np.zeros(k, dtype=np.int8)),
            "graphs": read_graphs(f),
            "scalar_params": _scalar_params(f),
        }


def read_trajectory(path: str | Path, k: int) -> dict[str, Any]:
    """One trajectory of a dataset file, without reading the others (`mpnode info --plot`).

    Returns:
        `{"time": [T], "states": [T, N, D], "hidden": {name: [T, ...]}}`.

    Raises:
        DatasetFormatError, FileNotFoundError: as `read_dataset`.
        ValueError: no trajectory `k` in the file.
    """
    with open_dataset(path) as f:
        _root_attrs(f)
        count = f["states"].shape[0]
        if not 0 <= k < count:
            raise ValueError(f"{path} has {count} trajectories (0 to {count - 1}), not {k}")
        hidden = {name: value[k] for name, value in f["hidden"].items()} if "hidden" in f else {}
        return {"time": f["time"][()], "states": f["states"][k], "hidden": hidden}


def _group(f: h5py.File, name: str) -> h5py.Group | dict:
    """An optional group (`params`), or an empty mapping when the file has none."""
    return f[name] if name in f else {}


def _scalar_params(f: h5py.File) -> dict[str, float]:
    return {name: float(v) for name, v in f["params"].attrs.items()} if "params" in f else {}


def _config(text: str) -> dict[str, Any]:
    """The stored generate config, in today's form (files written before the `solver`
    table held flat `rtol` and `atol`; the format version did not change, since older
    readers only show the config)."""
    config = json.loads(text)
    return upgrade_solver_fields(config) if isinstance(config, dict) else config


@contextmanager
def open_dataset(path: str | Path) -> Iterator[h5py.File]:
    """`with open_dataset(path) as f`: the file, for reading, once its virtual merge's
    shards are found; HDF5's errors inside the block (a damaged file: a chunk that fails
    its Fletcher-32 checksum, a broken object header) become one line naming the file and
    the array where it can.

    Raises:
        FileNotFoundError: no such file.
        DatasetFormatError: not HDF5, a virtual merge's missing shard, or a damaged file.
    """
    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(f"no such dataset file: {path}")
    try:
        f = h5py.File(path, "r")
    except OSError:
        raise DatasetFormatError(f"{path} is not an HDF5 file") from None
    with f:
        try:
            preflight(path)  # before `f` reads an attribute
            problems = virtual_source_problems(f)
            if problems:
                raise DatasetFormatError(f"{path}: {problems[0]}")
            yield f
        except HDF5_ERRORS as exc:
            raise DatasetFormatError(f"{path}: {name_damage(f, exc)}") from None


def _root_attrs(f: h5py.File) -> dict[str, Any]:
    """Root attributes as Python values, after checking the format name and version."""
    attrs = {key: _py(value) for key, value in f.attrs.items()}
    name = attrs.get("format")
    if name != FORMAT:
        what = f"format '{name}'" if name is not None else "no 'format' attribute"
        raise DatasetFormatError(f"{f.filename} is not an mpnode dataset ({what})")
    version = attrs.get("format_version")
    if not isinstance(version, int) or version < 1:
        raise DatasetFormatError(f"{f.filename} has an invalid format_version {version!r}")
    if version > FORMAT_VERSION:
        raise DatasetFormatError(
            f"{f.filename} is mpnode-dataset version {version}, newer than this mpnode "
            f"reads (up to {FORMAT_VERSION}): upgrade mpnode"
        )
    missing = [name for name in REQUIRED_ATTRS if name not in attrs]
    if missing:
        raise DatasetFormatError(f"{f.filename} lacks root attributes: {', '.join(missing)}")
    return {**OPTIONAL_ATTRS, **attrs}


def periodic_dims(state_names: Sequence[str], periodic_states: Sequence[str]
                  ) -> tuple[int, ...]:
    """The indices (in state order) of the `periodic_states` among `state_names`."""
    return tuple(i for i, name in enumerate(state_names) if name in set(periodic_states))


def _py(value: Any) -> Any:
    """numpy scalars and bytes from h5py attributes → plain Python values."""
    if isinstance(value, bytes):
        return value.decode(errors="replace")
    if isinstance(value, np.generic):
        return value.item()
    return value
