"""A user's own arrays, read and checked: trajectories (`load_states`: `.npy`, `.npz` or a
long-format CSV), a graph (`load_graph`: an adjacency array or an edge list), and the
initial states and controls `mpnode simulate` rolls out from (`load_initial_states`,
`load_controls`).

Each refusal is one line that names the file and what is wrong with it
(docs/dataset-format.md states the rules); `mpnode import` (`mpnode_cli.data.importers`)
and `mpnode simulate` read through here.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from mpnode_cli.data.arrays import nonfinite, read_arrays, read_table
from mpnode_cli.data.hdf5 import BLOCK_VALUES
from mpnode_cli.graphs.edge_files import missing_ids
from mpnode_cli.graphs.matrices import Graphs
from mpnode_cli.progress import Progress

# Columns of a long-format CSV besides the states (case does not matter).
CSV_INDEX = ("trajectory", "time", "node")


@dataclass(frozen=True)
class Loaded:
    """States read from a file.

    Attributes:
        states: `[K, T, N, D]` numbers: a read-only memory map of a `.npy` in its own
            dtype (read as it is used), float64 otherwise.
        names: `[D]` state names the file gives (CSV columns), or None.
        time: float64 `[T]` sample times the file gives, or None.
    """

    states: np.ndarray
    names: tuple[str, ...] | None = None
    time: np.ndarray | None = None


def load_states(path: str | Path, *, progress: Progress | None = None) -> Loaded:
    """Trajectories `[K, T, N, D]` from `.npy` (memory-mapped), `.npz` or a long-format
    `.csv`.

    A `.npz` holds them as `states` (or as its only array), and may hold `time [T]`. A
    CSV has a header row naming the columns `trajectory`, `time` and `node` (in any
    order) and one column per state component; each row is one node of one trajectory at
    one time. Trajectory and node ids are 0-based and contiguous, and every trajectory has
    a row for every node at every time (the same times for all).

    Args:
        path: the file.
        progress: called as the values are checked, a block of trajectories at a time.

    Raises:
        ValueError: an unreadable file, another shape, or values that are not finite.
    """
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix == ".csv":
        loaded = _read_csv(path)
    elif suffix in (".npy", ".npz"):
        arrays = read_arrays(path, mmap=True)
        if "states" in arrays:
            states = arrays["states"]
        elif len(arrays) == 1:
            states = next(iter(arrays.values()))
        else:
            raise ValueError(f"{path} holds arrays {', '.join(arrays)}: name the trajectories "
                             "'states'")
        time = arrays.get("time")
        loaded = Loaded(_numeric(states, path, "states"), None,
                        None if time is None else _numbers(time, path, "time"))
    else:
        raise ValueError(f"{path}: states must be a .npy, .npz or .csv file")
    states = loaded.states
    if states.ndim != 4:
        raise ValueError(f"{path}: states must be [K, T, N, D] (trajectories, samples, nodes, "
                         f"state components), got shape {list(states.shape)}")
    k, t, n, d = states.shape
    if k < 1 or t < 2 or n < 1 or d < 1:
        raise ValueError(f"{path}: states of shape {list(states.shape)}; a dataset needs at "
                         "least one trajectory, two samples, one node and one state")
    _finite(states, path, ("trajectory", "sample", "node", "component"), progress)
    return loaded


def load_graph(adjacency: str | Path | None, edge_list: str | Path | None, k: int, n: int,
               *, directed: bool = False) -> tuple[Graphs, np.ndarray]:
    """The graphs of `k` trajectories on `n` nodes: `(Graphs, graph_index int32 [K])`.

    Args:
        adjacency: `.npy` of `[N, N]` (one graph) or `[K, N, N]` (one per trajectory);
            each distinct graph is stored once (`graph_index` says which trajectory ran
            on which).
        edge_list: or a text file of `i j` lines (`mpnode_cli.graphs.edge_files.read_edges`), one
            graph for all, read without an `[N, N]` matrix.
        k, n: the trajectories' and nodes' count.
        directed: read the edge list's `i j` as the one edge i → j.

    Raises:
        ValueError: a graph that cannot be read, has another number of nodes than the
            states, or values other than 0 and 1.
    """
    from mpnode_cli.graphs.edge_files import read_edges

    if edge_list is not None:
        a = read_edges(edge_list, directed=directed)
        if a.num_nodes != n:
            raise ValueError(f"{edge_list} has {a.num_nodes} nodes (ids 0..{a.num_nodes - 1})"
                             f" but the states have {n}")
        return Graphs.from_edge_lists(n, [a]), np.zeros(k, dtype=np.int32)
    if adjacency is None:
        raise ValueError("give the graph as an adjacency array or an edge list")
    path = Path(adjacency)
    given = _numbers(_single(path), path, "adjacency")
    a = given[None] if given.ndim == 2 else given
    if a.ndim != 3 or a.shape[1:] != (n, n) or len(a) not in (1, k):
        raise ValueError(f"{path}: adjacency must be [N, N] (one graph) or [K, N, N] (one per "
                         f"trajectory) with N = {n}, K = {k}, got shape {list(given.shape)}")
    off = ~np.isin(a, (0, 1))
    if off.any():
        where = ", ".join(map(str, np.argwhere(off)[0]))
        raise ValueError(f"{path}: adjacency holds {a[off][0]:g} at [{where}]; mpnode's graphs "
                         "are unweighted: A[i, j] = 1 iff node j sends to node i, else 0")
    if len(a) == 1:
        return Graphs.from_adjacency(a.astype(np.uint8)), np.zeros(k, dtype=np.int32)
    unique, index = np.unique(a.astype(np.uint8), axis=0, return_inverse=True)
    return Graphs.from_adjacency(unique), index.reshape(k).astype(np.int32)


def load_initial_states(path: str | Path) -> np.ndarray:
    """Initial states `[K, N, D]` (or one, `[N, D]`) from `.npy` or `.npz`; float64.

    Raises:
        ValueError: an unreadable file, another shape, or values that are not finite.
    """
    path = Path(path)
    x0 = _numbers(_single(path), path, "initial states")
    if x0.ndim == 2:
        x0 = x0[None]
    if x0.ndim != 3 or 0 in x0.shape:
        raise ValueError(f"{path}: initial states must be [K, N, D] (trajectories, nodes, state "
                         f"components), got shape {list(x0.shape)}")
    _finite(x0, path, ("trajectory", "node", "component"))
    return x0


def load_controls(path: str | Path, ktn: tuple[int, int, int]) -> np.ndarray:
    """Controls `[K, T, N, U]` (zero-order hold) from `.npy` or `.npz`, checked against
    the states' K, T and N.

    Raises:
        ValueError: an unreadable file, another shape, or values that are not finite.
    """
    path = Path(path)
    u = _numbers(_single(path), path, "controls")
    if u.ndim != 4 or u.shape[:3] != ktn or u.shape[3] < 1:
        k, t, n = ktn
        raise ValueError(f"{path}: controls must be [K, T, N, U] with K = {k}, T = {t}, "
                         f"N = {n}, got shape {list(u.shape)}")
    _finite(u, path, ("trajectory", "sample", "node", "component"))
    return u


def _single(path: Path) -> np.ndarray:
    """The one array of a `.npy` (or a `.npz` holding one)."""
    if path.suffix.lower() not in (".npy", ".npz"):
        raise ValueError(f"{path}: expected a .npy (or .npz) file")
    arrays = read_arrays(path)
    if len(arrays) != 1:
        raise ValueError(f"{path} holds {len(arrays)} arrays ({', '.join(arrays)}); give one")
    return next(iter(arrays.values()))


def _numeric(a: np.ndarray, path: Path, what: str) -> np.ndarray:
    """`a` as it is (a memory map stays one), once its dtype is known to hold numbers."""
    if a.dtype.kind not in "biuf":
        raise ValueError(f"{path}: {what} must hold numbers, not {a.dtype}")
    return a


def _numbers(a: np.ndarray, path: Path, what: str) -> np.ndarray:
    return _numeric(a, path, what).astype(np.float64)


def _finite(a: np.ndarray, path: Path, axes: tuple[str, ...],
            progress: Progress | None = None) -> None:
    line = nonfinite(a, axes, values=BLOCK_VALUES, progress=progress)
    if line:
        raise ValueError(f"{path} {line}")


def _read_csv(path: Path) -> Loaded:
    columns, rows = read_table(path)
    if not columns:
        raise ValueError(f"{path} is empty: expected a header row naming trajectory, time, "
                         "node and the state columns")
    lower = [name.lower() for name in columns]
    missing = [name for name in CSV_INDEX if name not in lower]
    if missing:
        raise ValueError(f"{path}: the header lacks the column(s) {', '.join(missing)} (a long "
                         f"CSV has trajectory, time, node and one column per state)")
    names = tuple(c for c, low in zip(columns, lower, strict=True) if low not in CSV_INDEX)
    if not names:
        raise ValueError(f"{path}: no state columns besides trajectory, time and node")
    twice = sorted({c for c in names if names.count(c) > 1} | {c for c in CSV_INDEX
                                                                 if lower.count(c) > 1})
    if twice:
        raise ValueError(f"{path}: the header names {', '.join(twice)} more than once: give "
                         "each column its own name")
    if rows.shape[0] == 0:
        raise ValueError(f"{path} has a header but no rows")
    col = {name: rows[:, lower.index(name)] for name in CSV_INDEX}
    ids = {}
    for name in ("trajectory", "node"):
        v = col[name]
        if not (np.isfinite(v).all() and (v == np.round(v)).all() and v.min() >= 0):
            raise ValueError(f"{path}: {name} ids must be whole numbers from 0")
        # Contiguous ids from 0 are all below the row count: larger ones mean a gap, found
        # among the ids present (no range up to the largest, which may be any number).
        below = v < len(v)
        gaps = missing_ids(v[below].astype(np.int64), int(v.max()) + 1)
        if gaps:
            raise ValueError(f"{path}: {name} ids are 0-based and contiguous, but "
                             f"{', '.join(map(str, gaps))} never appear")
        ids[name] = v.astype(np.int64)
    if not np.isfinite(col["time"]).all():
        raise ValueError(f"{path}: the time column holds values that are not finite")
    times, t_index = np.unique(col["time"], return_inverse=True)
    k, t, n = int(ids["trajectory"].max()) + 1, len(times), int(ids["node"].max()) + 1
    flat = (ids["trajectory"] * t + t_index) * n + ids["node"]
    if len(np.unique(flat)) != len(flat):
        raise ValueError(f"{path}: a (trajectory, time, node) appears on more than one row")
    if len(flat) != k * t * n:
        raise ValueError(f"{path}: {len(flat)} rows, but {k} trajectories × {t} times × {n} "
                         f"nodes need {k * t * n}: every trajectory needs a row for every node "
                         "at every time (the same times for all)")
    states = np.empty((k * t * n, len(names)))
    state_cols = [i for i, low in enumerate(lower) if low not in CSV_INDEX]
    states[flat] = rows[:, state_cols]
    return Loaded(states.reshape(k, t, n, len(names)), names, times)
