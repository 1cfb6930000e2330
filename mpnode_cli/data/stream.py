"""Trajectories read from their dataset file as they are needed (`mpnode train --stream`).

`StreamedTrajectories` stands in for `TrajectoryData` when the states do not fit in
memory: it keeps only what is small — time, split, the G distinct graphs and each
trajectory's graph index — and reads a batch's states (and controls) from the HDF5 file
when asked (`take`). A batch read this way holds the very values `TrajectoryData.load`
would (float32 states, each trajectory's graph), so training on it gives the same losses.

- `select` and `subset` are views (no reading); `take` reads into a `TrajectoryData`.
- The file is pinned (`mpnode_cli.data.fingerprint.file_identity`) when it is opened: each
  read or pass (each epoch) refuses it, in one line, once it is replaced or rewritten.
- `prefetched(data, indices)` reads the batches ahead in a background thread, at most
  `depth` of them waiting (2 by default), while the model trains on the current one; the
  thread stops when the loop ends, fails or is interrupted.
- `fit_normalizer` fits the `Normalizer` in one pass over blocks of trajectories, with
  the pairwise combination of means and centred sums of squares of Chan, Golub and LeVeque
  ("Updating formulae and a pairwise algorithm for computing sample variances", 1979), in
  float64: the in-memory fit's result to rounding.
"""

from __future__ import annotations

import queue
import threading
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import h5py
import numpy as np
import torch

from mpnode_cli.data.dataset import Normalizer, TrajectoryData, _recipe, split_subset
from mpnode_cli.data.fingerprint import file_identity, fingerprint, same_file
from mpnode_cli.data.hdf5 import open_dataset, read_graphs, read_header
from mpnode_cli.data.reads import block_rows
from mpnode_cli.data.validate import require_valid
from mpnode_cli.graphs.matrices import EdgeBatch, Graphs

_STD_FLOOR = 1e-8  # as `Normalizer.fit`: a constant feature is centred, not divided by zero
# Values per read in whole-file passes (normalizer, fingerprint): about 32 MiB of float32.
_BLOCK_VALUES = 8 * 2**20


@dataclass(frozen=True)
class StreamedTrajectories:
    """Some trajectories of a dataset file, read on demand.

    Attributes:
        path: the file. rows: int64 `[K]`, the trajectories' indices in the file.
        graphs: the file's G distinct graphs. graph_index: int64 `[K_file]`.
        file_split: uint8 `[K_file]`. time: float64 `[T]`.
        shape: `(T, N, D)` of one trajectory; control_dim: U (0 if none).
        system, state_names, control_names, fingerprint, attrs: as `TrajectoryData`'s.
        identity: the file's when it was opened (`file_identity`), which every read checks.
    """

    path: Path
    rows: np.ndarray
    graphs: Graphs
    graph_index: np.ndarray
    file_split: np.ndarray
    time: torch.Tensor
    shape: tuple[int, int, int]
    control_dim: int
    system: str
    state_names: tuple[str, ...]
    control_names: tuple[str, ...]
    fingerprint: str
    attrs: dict[str, Any] = field(default_factory=dict)
    identity: tuple[int, ...] = ()

    @staticmethod
    def open(path: str | Path) -> StreamedTrajectories:
        """Check a dataset file completely (`require_valid`, which reads it in blocks) and
        keep what is small; the fingerprint is taken in blocks too."""
        identity = file_identity(path) if Path(path).exists() else ()
        require_valid(path)
        header = read_header(path)
        attrs, config = header["attrs"], header["attrs"]["config"]
        with open_dataset(path) as f:
            states = f["states"]
            graph_index = f["graph_index"][()].astype(np.int64)
            time = f["time"][()]
            rows = block_rows(states, _BLOCK_VALUES)
            graphs = read_graphs(f)
            digest = fingerprint(states, graphs, f["graph_index"][()], time, rows=rows,
                                 controls=f["controls"] if "controls" in f else None)
            shape = tuple(states.shape[1:])
            control_dim = f["controls"].shape[-1] if "controls" in f else 0
        topology = config.get("topology") if isinstance(config, dict) else None
        return StreamedTrajectories(
            path=Path(path), rows=np.arange(len(graph_index)),
            graphs=graphs,
            graph_index=graph_index, file_split=header["split"].astype(np.uint8),
            time=torch.from_numpy(np.asarray(time, dtype=np.float64)), shape=shape,
            control_dim=int(control_dim), system=attrs["system"],
            state_names=tuple(attrs["state_names"]),
            control_names=tuple(attrs["control_names"]), fingerprint=digest,
            attrs={"topology": topology, "config": config, "dt": attrs["dt"],
                   "recipe": _recipe(attrs.get("recipe")),
                   "prediction": attrs.get("prediction"),
                   "periodic_states": tuple(attrs["periodic_states"])}, identity=identity)

    def __len__(self) -> int:
        return len(self.rows)

    @property
    def num_nodes(self) -> int:
        return self.shape[1]

    @property
    def node_dim(self) -> int:
        return self.shape[2]

    @property
    def split(self) -> torch.Tensor:
        """uint8 `[K]`, the split of each of these trajectories."""
        return torch.from_numpy(self.file_split[self.rows])

    def graph(self, device: str | torch.device = "cpu") -> torch.Tensor | EdgeBatch:
        """Each trajectory's graph, as `TrajectoryData.graph` gives it: float32 `[K, N, N]`
        up to `DENSE_GRAPH_MAX_NODES` nodes (a view of the one graph when the file has one,
        no copy), else an `EdgeBatch`."""
        index = self.graph_index[self.rows]
        if not self.graphs.dense_ok:
            return self.graphs.batch(index, device)
        dense = torch.from_numpy(self.graphs.dense().astype(np.float32))  # [G, N, N]
        if len(dense) == 1:
            return dense.to(device).expand(len(self), *dense.shape[1:])
        return dense[torch.from_numpy(index)].to(device)

    def select(self, index: torch.Tensor) -> StreamedTrajectories:
        """The trajectories at `index` (`[K']` int64 or bool), still on disk."""
        return replace(self, rows=self.rows[np.asarray(index)])

    def subset(self, which: str) -> StreamedTrajectories:
        """One split ("train", "validation", "test") or "all", still on disk."""
        return split_subset(self, which)

    def take(self, index: torch.Tensor, f: h5py.File | None = None) -> TrajectoryData:
        """Read the trajectories at `index` into memory, as `TrajectoryData.take` gives them.

        Args:
            index: `[B]` int64 positions among these trajectories (any order).
            f: the file, already open (a pass over many batches opens it once).
        """
        rows = self.rows[np.asarray(index, dtype=np.int64).reshape(-1)]
        if f is None:
            with self.file() as f:
                return self.take(index, f)
        states = _read_rows(f["states"], rows)
        controls = None
        if self.control_dim > 0:
            controls = torch.from_numpy(_read_rows(f["controls"], rows))
        return TrajectoryData(
            states=torch.from_numpy(states), controls=controls, graphs=self.graphs,
            graph_index=torch.from_numpy(self.graph_index[rows]),
            time=self.time, split=torch.from_numpy(self.file_split[rows]), system=self.system,
            state_names=self.state_names, control_names=self.control_names, path=self.path,
            fingerprint=self.fingerprint, attrs=self.attrs)

    def blocks(self, values: int = _BLOCK_VALUES) -> Iterator[TrajectoryData]:
        """All these trajectories in order, about `values` state values at a time (fewer
        where they span many chunks: `block_rows`)."""
        with self.file() as f:
            per = block_rows(f["states"], values)
            for index in torch.arange(len(self)).split(per):
                yield self.take(index, f)

    @contextmanager
    def file(self) -> Iterator[h5py.File]:
        """The file, open for a read or a pass, once it is found to be the one opened."""
        same_file(self.path, self.identity)
        with open_dataset(self.path) as f:
            yield f

    def fit_normalizer(self) -> Normalizer:
        """`Normalizer.fit` of these trajectories' states and controls, in one pass."""
        x, u = _Moments(), _Moments()
        for block in self.blocks():
            x.add(block.states)
            if block.controls is not None:
                u.add(block.controls)
        x_mean, x_std = x.result()
        if self.control_dim == 0:
            return Normalizer(x_mean, x_std, torch.zeros(0), torch.zeros(0))
        return Normalizer(x_mean, x_std, *u.result())


def _read_rows(dataset: h5py.Dataset, rows: np.ndarray) -> np.ndarray:
    """float32 `[B, ...]`: `dataset[rows]`, rows in any order, repeats allowed.

    One read per row, in file order: a trajectory is one HDF5 chunk, and h5py's fancy
    indexing over a list of rows (or `read_direct` into the batch) is several times slower.
    """
    if len(rows) > 1 and (np.diff(rows) == 1).all():  # a block: one read
        return np.asarray(dataset[int(rows[0]):int(rows[-1]) + 1], dtype=np.float32)
    out = np.empty((len(rows), *dataset.shape[1:]), dtype=np.float32)
    for i in np.argsort(rows, kind="stable"):
        out[i] = dataset[int(rows[i])]
    return out


class _Moments:
    """Per-feature mean and population std of `[..., F]` blocks, combined pairwise."""

    def __init__(self) -> None:
        self.n, self.mean, self.m2 = 0, None, None

    def add(self, v: torch.Tensor) -> None:
        flat = v.reshape(-1, v.shape[-1]).double()  # (rows, F)
        n = flat.shape[0]
        if n == 0:
            return
        mean = flat.mean(dim=0)
        m2 = (flat - mean).pow(2).sum(dim=0)
        if self.mean is None:
            self.n, self.mean, self.m2 = n, mean, m2
            return
        total = self.n + n
        delta = mean - self.mean
        self.mean = self.mean + delta * (n / total)
        self.m2 = self.m2 + m2 + delta.pow(2) * (self.n * n / total)
        self.n = total

    def result(self) -> tuple[torch.Tensor, torch.Tensor]:
        if self.mean is None:
            raise ValueError("no trajectories to fit the normalization on")
        std = (self.m2 / self.n).sqrt()
        std = torch.where(std > _STD_FLOOR, std, torch.ones_like(std))
        return self.mean.float(), std.float()


def in_blocks(data: TrajectoryData | StreamedTrajectories) -> Iterator[TrajectoryData]:
    """All of `data` in order: in memory, itself; streamed, a block of trajectories at a
    time (`StreamedTrajectories.blocks`)."""
    if isinstance(data, TrajectoryData):
        yield data
    else:
        yield from data.blocks()


@contextmanager
def prefetched(data: TrajectoryData | StreamedTrajectories, indices: Sequence[torch.Tensor],
               depth: int = 2) -> Iterator[Iterator[TrajectoryData]]:
    """The batches `data.take(i)` for each `i` in `indices`, in order.

    In-memory data is taken as it is asked for. Streamed data is read by a background
    thread, at most `depth` batches ahead; leaving the block (at the end, on an error or
    on Ctrl-C) stops the thread and waits for it, so none outlives the loop. An error in
    the thread is raised in the loop, at the batch it could not read.
    """
    if isinstance(data, TrajectoryData):
        yield (data.take(index) for index in indices)
        return
    reader = _Reader(data, indices, depth)
    try:
        yield iter(reader)
    finally:
        reader.close()


class _Reader:
    """A thread that reads batches into a bounded queue, while the loop trains on the
    batch before (torch's kernels run without the GIL, so the two overlap)."""

    _DONE = object()

    def __init__(self, data: StreamedTrajectories, indices: Sequence[torch.Tensor],
                 depth: int):
        self.queue: queue.Queue = queue.Queue(maxsize=max(1, depth))
        self.stop = threading.Event()
        self.thread = threading.Thread(target=self._run, args=(data, list(indices)),
                                       name="mpnode-prefetch", daemon=True)
        self.thread.start()

    def _run(self, data: StreamedTrajectories, indices: list[torch.Tensor]) -> None:
        try:
            with data.file() as f:
                for index in indices:
                    if not self._put(data.take(index, f)):
                        return
        except BaseException as exc:  # handed to the loop, which raises it
            self._put(exc)
            return
        self._put(self._DONE)

    def _put(self, item: Any) -> bool:
        """Wait for room in the queue, or for `stop`; False when stopped."""
        while not self.stop.is_set():
            try:
                self.queue.put(item, timeout=0.1)
                return True
            except queue.Full:
                continue
        return False

    def __iter__(self) -> Iterator[TrajectoryData]:
        while True:
            item = self.queue.get()
            if item is self._DONE:
                return
            if isinstance(item, BaseException):
                raise item
            yield item

    def close(self) -> None:
        self.stop.set()
        while self.thread.is_alive():
            try:  # make room, so that a thread waiting to put sees `stop`
                self.queue.get_nowait()
            except queue.Empty:
                pass
            self.thread.join(timeout=0.05)
