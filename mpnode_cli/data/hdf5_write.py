"""Writing a dataset file (`write_dataset`), in the format `mpnode_cli.data.hdf5` defines
and reads: the root attributes, the states a block of trajectories at a time, the graphs as
edge lists (and matrices where small), and the rest of `Dataset`, through the atomic write.
"""

from __future__ import annotations

import json
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import h5py
import numpy as np

from mpnode_cli import __version__
from mpnode_cli.data.hdf5 import (
    BLOCK_VALUES,
    FORMAT,
    FORMAT_VERSION,
    PLAIN_GRAPHS_VERSION,
    ROOT_ATTRS,
    Dataset,
)
from mpnode_cli.data.integrity import create_array
from mpnode_cli.data.reads import block_rows
from mpnode_cli.graphs.matrices import Graphs
from mpnode_cli.progress import Progress


def write_dataset(path: str | Path, ds: Dataset, *, overwrite: bool = False,
                  progress: Progress | None = None) -> Path:
    """Write `ds` to `path` atomically.

    Args:
        path: target file; its folder is created if missing.
        ds: the dataset; shapes are checked against each other first.
        overwrite: replace an existing file (otherwise refuse).
        progress: called as the states are written, a block of trajectories at a time,
            with the trajectories written and K.

    Returns:
        The path written.

    Raises:
        FileExistsError: `path` exists and `overwrite` is False.
        ValueError: inconsistent shapes, or a target that is not a regular file or cannot
            be written (`mpnode_cli.paths.reserve_output`).
        KeyboardInterrupt: SIGINT or SIGTERM during the write; nothing is left behind.
    """
    from mpnode_cli.data.atomic import atomic_h5

    _check_shapes(ds)
    with atomic_h5(path, overwrite=overwrite) as (f, check):
        _write(f, ds, check, progress)
    return Path(path)


def _write(f: h5py.File, ds: Dataset, check: Any = lambda: None,
           progress: Progress | None = None) -> None:
    """Fill `f` with `ds`; `check()` between fields raises if the write should stop."""
    k, t, n, d = ds.states.shape
    provenance = {} if ds.seed is None else {"seed": int(ds.seed)}
    f.attrs.update(
        {
            **provenance,
            "format": FORMAT,
            "format_version": FORMAT_VERSION if ds.graphs.multigraph else PLAIN_GRAPHS_VERSION,
            "system": ds.system,
            "num_nodes": n,
            "node_dim": d,
            "control_dim": len(ds.control_names),
            "dt": float(ds.dt),
            "state_names": json.dumps(list(ds.state_names)),
            "control_names": json.dumps(list(ds.control_names)),
            "periodic_states": json.dumps(list(ds.periodic_states)),
            "config": json.dumps(ds.config, sort_keys=True),
            "mpnode_version": ds.mpnode_version or __version__,
            "created_utc": ds.created_utc or datetime.now(UTC).isoformat(timespec="seconds"),
        }
    )
    for key, value in ds.extra_attrs.items():
        if key in ROOT_ATTRS:
            raise ValueError(f"extra attribute '{key}' would overwrite a format attribute")
        f.attrs[key] = value
    create_array(f, "time", np.asarray(ds.time, dtype=np.float64))
    # One trajectory per chunk: training reads whole trajectories in random order.
    states = create_array(f, "states", shape=(k, t, n, d), dtype=ds.states.dtype,
                          chunks=(1, t, n, d))
    rows = block_rows(states, BLOCK_VALUES)  # a block of chunks: HDF5 keeps a record of each
    for start in range(0, k, rows):
        states[start:start + rows] = ds.states[start:start + rows]
        check()
        if progress is not None:
            progress(min(start + rows, k), k)
    check()
    if ds.controls is not None and len(ds.control_names) > 0:
        create_array(f, "controls", ds.controls, chunks=(1, *ds.controls.shape[1:]))
    _write_graphs(f, ds.graphs)
    create_array(f, "graph_index", np.asarray(ds.graph_index, dtype=np.int32))
    params = f.create_group("params")
    for name, value in ds.params.items():
        create_array(params, name, np.asarray(value, dtype=np.float64))
    for name, value in ds.scalar_params.items():
        params.attrs[name] = float(value)
    for name, value in ds.hidden.items():
        create_array(f, f"hidden/{name}", value, chunks=(1, *value.shape[1:]))
        check()
    create_array(f, "split", np.asarray(ds.split, dtype=np.uint8))
    status = np.zeros(k) if ds.solver_status is None else ds.solver_status
    n_f_evals = np.zeros(k) if ds.solver_n_f_evals is None else ds.solver_n_f_evals
    create_array(f, "solver/status", np.asarray(status, dtype=np.int8))
    create_array(f, "solver/n_f_evals", np.asarray(n_f_evals, dtype=np.int32))
    if ds.extrapolation is not None:
        create_array(f, "extrapolation", np.asarray(ds.extrapolation, dtype=np.uint8))


def _check_shapes(ds: Dataset) -> None:
    if ds.states.ndim != 4:
        raise ValueError(f"states must be [K, T, N, D], got shape {ds.states.shape}")
    k, t, n, d = ds.states.shape
    expected = {
        "time": (ds.time, (t,)),
        "graph_index": (ds.graph_index, (k,)),
        "split": (ds.split, (k,)),
    }
    if ds.controls is not None:
        expected["controls"] = (ds.controls, (k, t, n, len(ds.control_names)))
    for name, value in ds.hidden.items():
        expected[f"hidden/{name}"] = (value, (k, t, *value.shape[2:]))
    if ds.extrapolation is not None:
        expected["extrapolation"] = (ds.extrapolation, (k, n))
    if ds.graphs.num_nodes != n:
        raise ValueError(f"the graphs have {ds.graphs.num_nodes} nodes, the states {n}")
    for name, (array, shape) in expected.items():
        if np.shape(array) != shape:
            raise ValueError(f"{name} has shape {np.shape(array)}, expected {shape}")
    if len(ds.state_names) != d:
        raise ValueError(f"{len(ds.state_names)} state names for node_dim {d}")
    for what, names in (("state", ds.state_names), ("control", ds.control_names)):
        if len(set(names)) != len(names):  # `mpnode check` refuses such a file
            raise ValueError(f"{what} names {list(names)} repeat a name: each needs its own")
    if not set(ds.periodic_states) <= set(ds.state_names):
        raise ValueError(f"periodic_states {list(ds.periodic_states)} are not all among the "
                         f"state names {list(ds.state_names)}")
    if k and not 0 <= int(np.min(ds.graph_index)) <= int(np.max(ds.graph_index)) < len(
        ds.graphs
    ):
        raise ValueError("graph_index points outside the graphs")


def _write_graphs(f: h5py.File, graphs: Graphs) -> None:
    """`graph/edges [2, E]` int32 and `graph/num_edges [G]`, for every file; and
    `graph/adjacency [G, N, N]` uint8 when N ≤ `DENSE_GRAPH_MAX_NODES` (so that small
    files read as they always did, by h5py users and version 1 readers' habits alike)."""
    # int32 ids: half of int64 on disk, and 2³¹ nodes is beyond any graph mpnode solves.
    create_array(f, "graph/edges", np.stack([graphs.senders, graphs.receivers]).astype(
        np.int32).reshape(2, -1))
    create_array(f, "graph/num_edges", np.asarray(graphs.num_edges, dtype=np.int64))
    if graphs.dense_ok:
        create_array(f, "graph/adjacency", np.asarray(graphs.dense(), dtype=np.uint8))
