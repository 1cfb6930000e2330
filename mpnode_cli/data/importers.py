"""A user's own arrays as an mpnode dataset: `import_arrays(config) -> ImportSummary`.

Trajectories that mpnode did not generate (measurements, another simulator's output) come
as numpy arrays or a long-format CSV; their graph as an adjacency array or an edge list
(docs/dataset-format.md states the rules; `mpnode_cli.data.user_inputs` reads them). Every
input is checked before anything is written, and each refusal is one line that names the
file and what is wrong with it. The file written has system "custom", the resolved import
config with the sha256 of every input (its provenance), and the data's `fingerprint` as a
root attribute (the one training records, `mpnode_cli.data.fingerprint`).

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

from mpnode_cli.config.importer import ImportConfig
from mpnode_cli.data.fingerprint import fingerprint
from mpnode_cli.data.hdf5 import BLOCK_VALUES, Dataset
from mpnode_cli.data.hdf5_write import write_dataset
from mpnode_cli.data.user_inputs import load_controls, load_graph, load_states
from mpnode_cli.file_records import file_sha256
from mpnode_cli.progress import Progress, pass_of

# Relative slack when a time column or array is checked against dt.
_DT_RTOL = 1e-6


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
