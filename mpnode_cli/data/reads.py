"""Reads of an HDF5 array whose memory stays bounded, and arrays whose declared size the
file cannot hold.

HDF5 keeps a record of a few kB (its dataspaces and bookkeeping) for every chunk one read
touches, until the read ends. A dataset of many short trajectories is written one
trajectory per chunk, so a block of rows bounded in values alone (millions of values)
touches as many chunks as it has rows: 100,000 trajectories cost HDF5 about 0.7 GB for
one read of a few MB. `block_rows` bounds a read in chunks too, so that a pass over a
file (`mpnode check`, `info`, `train --stream`) holds one block, whatever the file's size.

An array's shape is only what its header declares: a file of 24 kB can declare 10⁷
trajectories whose chunks were never written, each read back as the fill value.
`unwritten` finds such an array from its index alone, before anything reads it.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from mpnode_cli.memory import format_bytes

# Chunks one read may touch: a few MB of HDF5's records per read.
CHUNKS_PER_READ = 1024


def block_rows(array: Any, values: int) -> int:
    """Rows (first axis) of `array` per read: at most `values` values, and for a chunked
    h5py dataset at most `CHUNKS_PER_READ` chunks; at least one row.

    Args:
        array: `[K, ...]`, a numpy array or an h5py dataset.
        values: the most values one read may hold.
    """
    per_row = max(1, int(np.prod(array.shape[1:])))
    rows = max(1, values // per_row)
    chunks = getattr(array, "chunks", None)
    if chunks:
        # Chunks one row of chunks spans; a read of r rows touches ceil(r / c0) of them.
        across = int(np.prod([-(-s // c) for s, c in zip(array.shape[1:], chunks[1:],
                                                          strict=True)]))
        rows = min(rows, max(1, CHUNKS_PER_READ // max(across, 1)) * chunks[0])
    return rows


def unwritten(name: str, array: Any, file_bytes: int) -> str | None:
    """One line where the (non-virtual) h5py dataset `array` declares more bytes than the
    file holds and was never written whole: chunks missing from its index, or a contiguous
    array with no storage. None otherwise (a compressed array may declare more than the
    file, written whole)."""
    declared = int(array.size) * array.dtype.itemsize
    if array.is_virtual or declared <= file_bytes:
        return None
    if array.chunks:
        spans = int(np.prod([-(-s // c) for s, c in zip(array.shape, array.chunks,
                                                        strict=True)]))
        written = array.id.get_num_chunks()
        if written >= spans:
            return None
        what = f"{written:,} of its {spans:,} chunks were written"
    elif array.id.get_storage_size() > 0:
        return None
    else:
        what = "none of it was written"
    return (f"array {name} declares shape {list(array.shape)} ({format_bytes(declared)}) in "
            f"a file of {format_bytes(file_bytes)}: {what}; the file is damaged or was never "
            "finished, write it again")

