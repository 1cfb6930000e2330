"""A user's graph as a text file of edges: `i j` lines (networkx's `write_edgelist`), with
an optional weight column of 0 or 1, read into an `EdgeList` or a matrix.

What a file may hold, and what is refused in one line, is in `read_edges`; the graph
conventions are `mpnode_cli.graphs.matrices`'.
"""

from __future__ import annotations

from array import array
from pathlib import Path

import numpy as np

from mpnode_cli.graphs.matrices import EdgeList
from mpnode_cli.textfiles import text_lines

# The largest graph read from a file (`read_edges`): ids 0..MAX_EDGE_FILE_NODES − 1. Ids are
# checked as they are read, so a stray number (a timestamp, a hash, a typo of 20 digits) is
# refused before anything is sized by it. 2²⁴ nodes is far beyond the graphs mpnode
# simulates: one float32 state per node is 64 MiB per sample, and at mean degree 10 one
# trajectory's messages alone are 40 × `mpnode_cli.graphs.matrices.EDGE_ROWS`.
MAX_EDGE_FILE_NODES = 2**24
# The longest line of an edge list: `i j w` lines are short, so a longer one (a binary file
# without newlines) is refused without reading it whole.
_LINE_CHARS = 4096

def read_edge_list(path: str | Path, *, directed: bool = False) -> np.ndarray:
    """`read_edges` as a uint8 `[n, n]` adjacency matrix (zero diagonal; symmetric unless
    `directed`)."""
    return read_edges(path, directed=directed).to_dense()


def read_edges(path: str | Path, *, directed: bool = False) -> EdgeList:
    """Read a graph from a text file of `i j` lines.

    Each line `i j` is an edge between nodes i and j: undirected by default (messages go
    both ways, `A[i, j] = A[j, i] = 1`), or with `directed` one edge from sender i to
    receiver j (`A[j, i] = 1`). A line holding one id `i` declares a node without edges.
    Node ids are 0-based integers below `MAX_EDGE_FILE_NODES` and must be contiguous: the
    graph has `max id + 1` nodes, and every id below the largest must appear on some line (a
    gap is refused, as it is more often a typo or a 1-based file than a wanted isolated
    node; declare an isolated node on a line of its own). Blank lines and `#` comments are
    skipped; duplicate edges are merged. Ids may be separated by spaces, tabs or a comma.

    A third column is the edge's weight, as networkx's `write_weighted_edgelist` writes
    it. mpnode's graphs are unweighted (a dataset's adjacency holds 0 and 1,
    docs/dataset-format.md), so a weight must be 1 (the edge) or 0 (no edge; its ids still
    count as nodes); any other weight is refused rather than silently rounded.

    Memory grows with the file's lines, never with the size of an id: ids are checked
    against `MAX_EDGE_FILE_NODES` as they are read, and gaps are found among the ids present.

    Args:
        path: the text file (UTF-8).
        directed: read `i j` as the one edge i → j instead of an undirected edge.

    Returns:
        The graph's `EdgeList` (each undirected edge once each way; no `[n, n]` matrix).

    Raises:
        ValueError: a file that cannot be read or is not text, a malformed line, an id
            that is negative or not below `MAX_EDGE_FILE_NODES`, a self-loop, a gap in the
            ids, or no edges at all (each names the file, and the line where there is one).
    """
    ends = array("q")  # i, j of each edge of weight 1, one after another
    ids = array("q")  # every id on any line
    for lineno, raw in text_lines(path, "edge list", _LINE_CHARS):
        line = raw.split("#", 1)[0].replace(",", " ").strip()
        if not line:
            continue
        fields = line.split()
        where = f"{path}:{lineno}"
        if len(fields) not in (1, 2, 3):
            raise ValueError(f"{where}: expected two node ids 'i j' and an optional weight "
                             f"(or one id, for a node without edges), got {_shown(raw)}")
        weight = _weight(fields.pop(), where) if len(fields) == 3 else 1.0
        try:
            pair = [int(x) for x in fields]
        except ValueError:
            raise ValueError(f"{where}: node ids must be integers, got {_shown(raw)}") from None
        if min(pair) < 0:
            raise ValueError(f"{where}: node ids are 0-based and non-negative, got "
                             f"{' '.join(fields)}")
        if max(pair) >= MAX_EDGE_FILE_NODES:
            raise ValueError(f"{where}: node id {max(pair)} is beyond the largest graph mpnode "
                             f"reads ({MAX_EDGE_FILE_NODES:,} nodes, "
                             f"ids 0..{MAX_EDGE_FILE_NODES - 1})")
        ids.extend(pair)
        if len(pair) == 1:
            continue
        if pair[0] == pair[1]:
            raise ValueError(f"{where}: self-loop {pair[0]} {pair[0]} is not allowed")
        if weight:
            ends.extend(pair)
    if not ends:
        raise ValueError(f"{path}: no edges found (expected lines of 'i j')")
    present = np.frombuffer(ids, dtype=np.int64)
    n = int(present.max()) + 1
    gaps = missing_ids(present, n, count=6)
    if gaps:
        shown = ", ".join(map(str, gaps[:5])) + (" ..." if len(gaps) > 5 else "")
        raise ValueError(f"{path}: node ids {shown} appear on no line, yet the largest id is "
                         f"{n - 1}; ids are 0-based and contiguous (list a node without edges "
                         "on a line of its own)")
    ij = np.frombuffer(ends, dtype=np.int64).reshape(-1, 2)  # [E, 2], sender i, receiver j
    senders, receivers = ij[:, 0], ij[:, 1]
    if not directed:
        senders, receivers = (np.concatenate([senders, receivers]),
                              np.concatenate([receivers, senders]))
    return EdgeList.build(n, senders, receivers)  # duplicates merged


def _shown(raw: str) -> str:
    """A line as an error message quotes it: stripped, and cut short if long."""
    text = raw.strip()
    return repr(text if len(text) <= 60 else text[:57] + "...")


def missing_ids(ids: np.ndarray, stop: int, count: int = 5) -> list[int]:
    """The first `count` integers of `0..stop − 1` that `ids` lacks.

    Found from the ids present (sorted, with the run of missing ids before each), so the
    cost grows with `len(ids)`, not with `stop`: one stray id of 10¹⁵ costs no range of
    that length.

    Args:
        ids: integers `[M]`, each in `0..stop − 1` (repeats allowed).
        stop: one past the largest id there should be (a Python int, of any size).
        count: how many missing ids to return at most.
    """
    present = np.unique(np.asarray(ids, dtype=np.int64))  # sorted
    before = np.diff(present, prepend=-1) - 1  # ids missing just below each id present
    missing: list[int] = []
    for i in np.flatnonzero(before):
        first = int(present[i] - before[i])
        missing.extend(range(first, min(int(present[i]), first + count - len(missing))))
        if len(missing) >= count:
            return missing
    tail = int(present[-1]) + 1 if len(present) else 0  # the run after the largest present
    missing.extend(range(tail, min(stop, tail + count - len(missing))))
    return missing


def _weight(text: str, where: str) -> float:
    """An edge list's weight column: 1 (an edge) or 0 (none); anything else is refused."""
    try:
        weight = float(text)
    except ValueError:
        raise ValueError(f"{where}: an edge weight must be a number, got {text!r}") from None
    if weight not in (0.0, 1.0):
        raise ValueError(f"{where}: edge weight {text} is not 0 or 1; mpnode's graphs are "
                         "unweighted (an adjacency holds 0 and 1, docs/dataset-format.md)")
    return weight
