"""The graphs of a dataset file, checked (`mpnode_cli.data.validate`'s part for
`graph/`): the edge lists and their counts, the matrices where stored and their agreement
with the edges, and `graph_index`; with the primitives every check of an open file uses.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

import h5py
import numpy as np

from mpnode_cli.graphs.matrices import DENSE_GRAPH_MAX_NODES, Graphs, degree_range
from mpnode_cli.limits import MULTIPLICITY_MAX

if TYPE_CHECKING:
    from mpnode_cli.data.validate import Report


class FileChecks:
    """One pass over an open file: each method adds problems and summary facts to a
    `Report`. This class checks the graphs; `validate` adds the rest of the file."""

    def __init__(self, f: h5py.File, report: Report):
        self.f, self.report = f, report
        self.problems, self.summary = report.problems, report.summary
        self.edge_graphs: Graphs | None = None  # version 2's edge lists, once checked

    def problem(self, text: str) -> None:
        self.problems.append(text)

    def _array(self, name: str, *, required: bool) -> h5py.Dataset | None:
        if name not in self.f:
            if required:
                self.problem(f"missing dataset '{name}'")
            return None
        obj = self.f[name]
        if not isinstance(obj, h5py.Dataset):
            self.problem(f"'{name}' must be a dataset, not a group")
            return None
        if obj.dtype.kind not in "biuf":
            self.problem(f"'{name}' must hold numbers, not {obj.dtype}")
            return None
        return obj

    def _shape(self, name: str, obj: h5py.Dataset, want: tuple, meaning: str) -> bool:
        """Shape `want` (None: any size on that axis); a problem if it differs."""
        ok = len(obj.shape) == len(want) and all(
            w is None or s == w for s, w in zip(obj.shape, want, strict=True))
        if not ok:
            shown = ", ".join("*" if w is None else str(w) for w in want)
            self.problem(f"{name} has shape {list(obj.shape)}, expected [{shown}] {meaning}")
        return ok

    def _graph(self, k: int, n: int, version: Any) -> int:
        """The graphs: edge lists (version 2) and the matrices (required in version 1,
        optional in version 2, where they must agree with the edges; version 4 allows a
        multigraph: an edge of multiplicity w is w messages, and w in the matrix); returns G."""
        v1 = version == 1
        multi = is_int(version) and version >= 4
        before, in_degree = len(self.problems), None
        g = self._edges(n, multi) if not v1 else None
        adjacency = self._array("graph/adjacency", required=v1)
        if adjacency is not None and self._shape("graph/adjacency", adjacency, (None, n, n),
                                                  "[G, N, N]"):
            if g is not None and adjacency.shape[0] != g:
                self.problem(f"graph/adjacency holds {adjacency.shape[0]} graphs but "
                             f"graph/num_edges {g}")
            g = adjacency.shape[0]
            if g < 1:
                self.problem("graph/adjacency holds no graph (G = 0)")
            # Above the threshold a matrix is only scanned, one graph at a time; the same
            # pass sums its rows: the in-degrees of version 1, which has no edge lists.
            in_degree, bad = np.zeros((g, n), np.int64), False
            for i in range(g):
                matrix = adjacency[i]
                if not _counts(matrix, multi):
                    bad = True
                    break
                in_degree[i] = matrix.sum(axis=1)
            if bad:
                self.problem("graph/adjacency must hold only 0 and 1 "
                             "(A[g, i, j] = 1 iff node j sends to node i)" if not multi else
                             "graph/adjacency must hold whole numbers 0–255 (A[g, i, j] the "
                             "edges from node j to node i)")
            elif self.edge_graphs is not None and n <= DENSE_GRAPH_MAX_NODES and (
                    len(self.edge_graphs) == g):
                stored = adjacency[()] if multi else adjacency[()] != 0
                if not np.array_equal(self.edge_graphs.dense(), stored):
                    self.problem("graph/adjacency and graph/edges hold different graphs")
        g = g or 0
        self.summary["graphs"] = g
        if self.edge_graphs is not None:
            in_degree = self.edge_graphs.in_degree()  # [G, N], parallel edges w times
        if g and in_degree is not None and len(self.problems) == before:
            self.summary["in_degree"] = degree_range(in_degree)
        index = self._array("graph_index", required=True)
        if index is not None and self._shape("graph_index", index, (k,), "[K]"):
            if index.dtype.kind not in "iu":
                self.problem(f"graph_index must be integers, not {index.dtype}")
            elif k and g and not (0 <= int(np.min(index)) and int(np.max(index)) < g):
                self.problem(f"graph_index points outside the graphs: values "
                             f"{int(np.min(index))}..{int(np.max(index))}, graphs 0..{g - 1}")
        return g

    def _edges(self, n: int, multi: bool = False) -> int | None:
        """`graph/edges [2, E]` and `graph/num_edges [G]`: ids in 0..N−1, counts that add
        up, no message twice within a graph unless `multi` (format version 4: a multigraph).
        Returns G (None when unreadable)."""
        edges = self._array("graph/edges", required=True)
        counts = self._array("graph/num_edges", required=True)
        if edges is None or counts is None:
            return None
        ok = self._shape("graph/edges", edges, (2, None), "[2, E] (senders, receivers)")
        ok &= self._shape("graph/num_edges", counts, (None,), "[G]")
        if not ok:
            return None
        if edges.dtype.kind not in "iu" or counts.dtype.kind not in "iu":
            self.problem("graph/edges and graph/num_edges must be integers")
            return None
        g, ids, per_graph = counts.shape[0], edges[()].astype(np.int64), counts[()]
        if g < 1:
            self.problem("graph/num_edges holds no graph (G = 0)")
        if (per_graph < 0).any() or int(per_graph.sum()) != ids.shape[1]:
            self.problem(f"graph/num_edges adds up to {int(per_graph.sum())} but graph/edges "
                         f"holds {ids.shape[1]} edges")
            return g
        if ids.size and (ids.min() < 0 or ids.max() >= n):
            self.problem(f"graph/edges holds node ids {int(ids.min())}..{int(ids.max())}; "
                         f"they must lie in 0..{n - 1}")
            return g
        graph_of_edge = np.repeat(np.arange(g, dtype=np.int64), per_graph)
        key = (graph_of_edge * n + ids[1]) * n + ids[0]
        if not multi and len(np.unique(key)) != len(key):
            self.problem("graph/edges holds a message twice within a graph (graphs are "
                         "unweighted: each sender → receiver pair at most once, unless "
                         "format_version 4 says it is a multigraph)")
        else:
            self.edge_graphs = Graphs.from_concatenated(n, ids[0], ids[1], per_graph)
        self.summary["edges"] = int(ids.shape[1])
        return g


def is_int(value: Any) -> bool:
    return isinstance(value, int) and not isinstance(value, bool)


def _counts(matrix: np.ndarray, multi: bool) -> bool:
    """Whether an adjacency matrix holds 0 and 1, or (`multi`) whole numbers 0–255."""
    if not multi:
        return bool(np.isin(matrix, (0, 1)).all())
    values = np.asarray(matrix)
    return bool(((values >= 0) & (values <= MULTIPLICITY_MAX)
                 & (values == np.round(values))).all())
