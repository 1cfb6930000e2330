"""A dataset's identity: `fingerprint`, the sha256 of its data, whatever file holds them.

Runs and checkpoints record the fingerprint of the data they trained on; `mpnode train`
refuses the same data twice, `train --resume` other data, and `evaluate` finds a
checkpoint's own training file by it. Two files with the same fingerprint hold the same
trajectories on the same graphs at the same times, with the same controls.

A file read again and again while a run goes on (`mpnode train --stream`, each epoch) is
pinned by a cheaper identity, `file_identity`: replaced or rewritten, it is refused
(`same_file`) rather than trained on as if it were the data the run began with.
"""

from __future__ import annotations

import hashlib
import os
from pathlib import Path
from typing import Any

import numpy as np

from mpnode_cli.graphs.matrices import Graphs
from mpnode_cli.progress import Progress


def fingerprint(states: Any, graphs: Graphs, graph_index: np.ndarray,
                time: np.ndarray, *, controls: Any = None, rows: int | None = None,
                progress: Progress | None = None) -> str:
    """The data's identity: sha256 of states (as float32), the graphs, graph_index and
    time, each as stored, then the controls (as float32) where there are any.

    The graphs enter as `Graphs.fingerprint_arrays`: the `[G, N, N]` matrices up to
    `DENSE_GRAPH_MAX_NODES` nodes (so a file's fingerprint is the one format version 1
    gave it), the edge lists above. Controls come last and only when there are some, so a
    dataset without them keeps the fingerprint it had before controls counted.

    Args:
        states: `[K, T, N, D]`, a numpy array or an h5py dataset (read `rows`
            trajectories at a time; the digest is the same).
        graphs, graph_index, time: as stored in the file.
        controls: `[K, T, N, U]` (numpy or h5py), or None.
        rows: trajectories per read (default: all at once).
        progress: called after each read of the states, with the trajectories read and K.
    """
    digest = hashlib.sha256()
    step = max(1, rows or len(states))
    _blocks(digest, states, step, progress)
    for array in (*graphs.fingerprint_arrays(), graph_index, time):
        digest.update(np.ascontiguousarray(array).tobytes())
    if controls is not None and controls.shape[-1] > 0:
        _blocks(digest, controls, step, None)
    return digest.hexdigest()


def _blocks(digest, values: Any, step: int, progress: Progress | None) -> None:
    """Add `values` to `digest` as float32, `step` trajectories at a time."""
    for start in range(0, len(values), step):
        block = np.asarray(values[start:start + step], dtype=np.float32)
        digest.update(np.ascontiguousarray(block).tobytes())
        if progress is not None:
            progress(min(start + step, len(values)), len(values))


def file_identity(path: str | Path) -> tuple[int, ...]:
    """A file's cheap identity: its device, inode, size and modification time (ns)."""
    stat = os.stat(path)
    return stat.st_dev, stat.st_ino, stat.st_size, stat.st_mtime_ns


def same_file(path: str | Path, identity: tuple[int, ...]) -> None:
    """Refuse `path` unless it is still the file of `identity` (`file_identity`; an empty
    one pins nothing).

    Raises:
        ValueError: the file was replaced, rewritten or removed (one line).
    """
    try:
        now = file_identity(path)
    except OSError:
        now = ()
    if identity and now != identity:
        raise ValueError(f"{path} changed while this run was reading it (replaced, rewritten "
                         "or removed): a run trains on the data it began with; put that file "
                         "back and resume, or start a new run on the new data")
