"""A user's own arrays as an mpnode dataset: `import_arrays(config) -> ImportSummary`.

Trajectories that mpnode did not generate (measurements, another simulator's output) come
as numpy arrays or a long-format CSV; their graph as an adjacency array or an edge list
(docs/dataset-format.md states the rules). Every input is checked before anything is
written, and each refusal is one line that names the file and what is wrong with it. The
file written has system "custom", the resolved import config with the sha256 of every
input (its provenance), and the data's `fingerprint` as a root attribute (the one training
records, `mpnode_cli.data.hdf5.fingerprint`).

A `.npy` of states is memory-mapped and passed through a block of trajectories at a time
(checked, fingerprinted, cast and written), so an import needs about one block of memory
besides the mapped file, whatever its size. Nothing here prints; the CLI (`mpnode import`)
turns a `ValueError` into its one line, and shows `progress`.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from mpnode_cli.config import ImportConfig
from mpnode_cli.data.arrays import nonfinite, read_arrays, read_table
from mpnode_cli.data.fingerprint import fingerprint
from mpnode_cli.data.hdf5 import BLOCK_VALUES, Dataset, write_dataset
from mpnode_cli.edge_files import missing_ids
from mpnode_cli.graphs import Graphs
from mpnode_cli.paths import file_sha256
from mpnode_cli.progress import Progress, pass_of

# Columns of a long-format CSV besides the states (case does not matter).
CSV_INDEX = ("trajectory", "time", "node")
# Relative slack when a time column or array is checked against dt.
_DT_RTOL = 1e-6


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


@dataclass(frozen=True)
class ImportSummary:
    """What `import_arrays` wrote.

    Attributes:
        path: the file. trajectories, samples, nodes, node_dim, control_dim: K, T, N, D, U.
        graphs: distinct graphs stored. split_counts: train, validation, test.
        fingerprint: the data's fingerprint.
    """

    path: Path
    trajectories: int
    samples: int
    nodes: int
    node_dim: int
    control_dim: int
    graphs: int
    split_counts: tuple[int, int, int]
    fingerprint: str


def import_arrays(config: ImportConfig, *, overwrite: bool = False,
                  progress: Progress | None = None) -> ImportSummary:
    """Read, check and write the dataset `config` describes.

    Args:
        config: what to import.
        overwrite: replace an existing regular file at the output path.
        progress: called as `progress(done, total)` while the states are checked,
            fingerprinted and written (three passes over the K trajectories: total 3K).

    Raises:
        ValueError: an input that cannot be read or does not fit the others (one line),
            or an output path that cannot be written or is one of the inputs (checked and
            reserved before anything is read, `mpnode_cli.paths.reserve_output`).
        FileExistsError: the output exists and `overwrite` is False.
        KeyboardInterrupt: SIGINT or SIGTERM during the write; nothing is left behind.
    """
    from mpnode_cli.paths import reserve_output

    out = output_path(config)
    inputs = (config.states, config.adjacency, config.edge_list, config.controls)
    with reserve_output(out, overwrite=overwrite, inputs=inputs):
        return _import(config, out, progress)


def _import(config: ImportConfig, out: Path, progress: Progress | None) -> ImportSummary:
    """`import_arrays` once its output is reserved: read, check, write."""
    from mpnode_cli.data.splits import split_trajectories

    loaded = load_states(config.states, progress=pass_of(progress, 0, 3))
    states = loaded.states
    k, t, n, d = states.shape
    time = _time(loaded.time, config.dt, t, config.states)
    names = _names(config.state_names, loaded.names, d, "state", "x", config.states)
    graphs, graph_index = load_graph(config.adjacency, config.edge_list, k, n,
                                     directed=config.directed)
    controls, control_names = None, ()
    if config.controls is not None:
        controls = load_controls(config.controls, (k, t, n))
        control_names = _names(config.control_names, None, controls.shape[3], "control",
                               "u", config.controls)
    elif config.control_names:
        raise ValueError("--control-names given without --controls")
    periodic = periodic_names(config.periodic, names)
    split = split_trajectories(k, config.split, config.seed)
    stored = _Cast(states, config.dtype)
    digest = fingerprint(stored, graphs, graph_index, time, controls=controls, rows=_rows(states),
                         progress=pass_of(progress, 1, 3))
    sources = {name: {"path": str(path.resolve()), "sha256": file_sha256(path)}
               for name in ("states", "adjacency", "edge_list", "controls")
               if (path := getattr(config, name)) is not None}
    resolved = config.model_copy(update={"out": out, "state_names": list(names),
                                         "control_names": list(control_names)})
    provenance = {"verb": "import", **resolved.model_dump(mode="json"),
                  "topology": "edgelist" if config.edge_list is not None else "adjacency",
                  "sources": sources}
    write_dataset(out, Dataset(
        system="custom", dt=config.dt, state_names=names, control_names=control_names,
        seed=config.seed, config=provenance, time=time, states=stored,
        controls=None if controls is None else controls.astype(config.dtype),
        graphs=graphs, graph_index=graph_index, split=split, periodic_states=periodic,
        extra_attrs={"fingerprint": digest}),
        overwrite=True,  # over the reservation `import_arrays` made
        progress=pass_of(progress, 2, 3))
    counts = np.bincount(split, minlength=3)
    return ImportSummary(path=out, trajectories=k, samples=t, nodes=n, node_dim=d,
                         control_dim=len(control_names), graphs=len(graphs),
                         split_counts=(int(counts[0]), int(counts[1]), int(counts[2])),
                         fingerprint=digest)


class _Cast:
    """`array` as `dtype`, a block at a time: `cast[a:b]` reads and casts those rows only,
    so a memory-mapped input is never copied whole."""

    def __init__(self, array: Any, dtype: str):
        self.array, self.dtype = array, np.dtype(dtype)
        self.shape, self.ndim = array.shape, array.ndim

    def __len__(self) -> int:
        return len(self.array)

    def __getitem__(self, index: Any) -> np.ndarray:
        return np.asarray(self.array[index], dtype=self.dtype)


def _rows(array: Any) -> int:
    """Rows (trajectories) per block of `BLOCK_VALUES` values."""
    return max(1, BLOCK_VALUES // max(1, int(np.prod(array.shape[1:]))))


def output_path(config: ImportConfig) -> Path:
    """`config.out`, or `datasets/<states file stem>.h5`."""
    return Path(config.out) if config.out is not None else Path(
        "datasets", f"{Path(config.states).stem}.h5")


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
        edge_list: or a text file of `i j` lines (`mpnode_cli.edge_files.read_edges`), one
            graph for all, read without an `[N, N]` matrix.
        k, n: the trajectories' and nodes' count.
        directed: read the edge list's `i j` as the one edge i → j.

    Raises:
        ValueError: a graph that cannot be read, has another number of nodes than the
            states, or values other than 0 and 1.
    """
    from mpnode_cli.edge_files import read_edges

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


def _time(given: np.ndarray | None, dt: float, t: int, path: Path) -> np.ndarray:
    """Sample times `t₀ + i·dt`, with t₀ from the file's times (0 without them), which
    must step by `dt`."""
    if given is None:
        return np.arange(t) * dt
    if given.shape != (t,):
        raise ValueError(f"{path}: time has shape {list(given.shape)}, expected [{t}]")
    steps = np.diff(given)
    off = np.abs(steps - dt) > _DT_RTOL * dt + 1e-9 * float(np.abs(given).max())
    if off.any():
        i = int(np.argmax(off))
        raise ValueError(f"{path}: time steps by {steps[i]:g} between samples {i} and {i + 1}, "
                         f"but --dt is {dt:g}; samples must be evenly spaced by dt")
    return given[0] + np.arange(t) * dt


def periodic_names(given: list[str], names: tuple[str, ...]) -> tuple[str, ...]:
    """`--periodic` names, checked: each a state name, none twice (in state order).

    Raises:
        ValueError: a name that is not one of `names`, or one given twice (one line).
    """
    for name in given:
        if name not in names:
            raise ValueError(f"--periodic {name!r} is not a state name (states: "
                             f"{', '.join(names)})")
    if len(set(given)) != len(given):
        raise ValueError(f"--periodic names a state twice: {', '.join(given)}")
    return tuple(name for name in names if name in given)


def _names(given: list[str] | None, found: tuple[str, ...] | None, size: int, what: str,
           prefix: str, path: Path) -> tuple[str, ...]:
    if given:
        if len(given) != size:
            raise ValueError(f"{len(given)} {what} names given for {size} {what} components "
                             f"in {path}")
        return tuple(given)
    return found if found is not None else tuple(f"{prefix}{i}" for i in range(size))
