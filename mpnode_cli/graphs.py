"""Graph topologies as dense adjacency matrices, and their edge lists.

Convention (used by every dataset and model): `A[i, j] = 1` iff node j sends a message to
node i, i.e. row i lists the senders of receiver i. All generated graphs are undirected, so
`A` is symmetric with a zero diagonal. `edges(A)` gives the jraph/PyG form
`(senders, receivers)`.

Random graphs come from networkx with an explicit integer seed. The authors' graphs came
from LightGraphs.jl (MersenneTwister streams) and cannot be reproduced from Python, which
is why every dataset stores its adjacency (docs/systems.md).

networkx is imported inside the functions that need it, so that importing this module (and
the system registry, which imports it) stays cheap for the CLI.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

TOPOLOGIES: tuple[str, ...] = ("complete", "chain", "er", "ba", "ws")

# Keyword arguments each topology accepts; anything else is a caller's mistake.
_KWARGS: dict[str, tuple[str, ...]] = {
    "complete": (),
    "chain": (),
    "er": ("p", "m_edges"),
    "ba": ("m",),
    "ws": ("k", "p"),
}


def make_graph(topology: str, n: int, seed: int, **kw: float) -> np.ndarray:
    """Build an undirected graph and return its adjacency matrix.

    Args:
        topology: one of `TOPOLOGIES`: `complete`; `chain` (path 0-1-...-n-1); `er`
            Erdős–Rényi, with `p` (G(n, p)) or `m_edges` (G(n, M), exactly M edges);
            `ba` Barabási–Albert with `m` edges per new node; `ws` Watts–Strogatz with
            ring degree `k` (k // 2 neighbours per side) and rewiring probability `p`.
        n: number of nodes, at least 1.
        seed: seed of the random generators (ignored by deterministic topologies).
        **kw: the topology's parameters, as above.

    Returns:
        uint8 `[n, n]`, symmetric, zero diagonal.

    Raises:
        ValueError: unknown topology, missing/unexpected parameters, or parameters that
            the topology cannot satisfy at this size.
    """
    import networkx as nx

    if topology not in _KWARGS:
        raise ValueError(f"unknown topology '{topology}' (choose from: {', '.join(TOPOLOGIES)})")
    unexpected = sorted(set(kw) - set(_KWARGS[topology]))
    if unexpected:
        accepted = ", ".join(_KWARGS[topology]) or "none"
        raise ValueError(
            f"topology '{topology}' does not take {', '.join(unexpected)} (accepted: {accepted})"
        )
    if n < 1:
        raise ValueError(f"a graph needs at least 1 node, got n={n}")

    if topology == "complete":
        g = nx.complete_graph(n)
    elif topology == "chain":
        g = nx.path_graph(n)
    elif topology == "er":
        g = _erdos_renyi(n, seed, **kw)
    elif topology == "ba":
        m = int(_require(kw, "m", topology))
        if not 1 <= m < n:
            raise ValueError(f"Barabási–Albert needs 1 <= m < n, got m={m}, n={n}")
        g = nx.barabasi_albert_graph(n, m, seed=seed)
    else:  # ws
        k, p = int(_require(kw, "k", topology)), float(_require(kw, "p", topology))
        if not 0 <= k < n or not 0.0 <= p <= 1.0:
            raise ValueError(f"Watts–Strogatz needs 0 <= k < n and 0 <= p <= 1, got k={k}, p={p}")
        g = nx.watts_strogatz_graph(n, k, p, seed=seed)
    return nx.to_numpy_array(g, nodelist=range(n), dtype=np.uint8)


def _erdos_renyi(n: int, seed: int, p: float | None = None, m_edges: int | None = None):
    import networkx as nx

    if (p is None) == (m_edges is None):
        raise ValueError("topology 'er' takes exactly one of p (G(n, p)) or m_edges (G(n, M))")
    if p is not None:
        if not 0.0 <= p <= 1.0:
            raise ValueError(f"Erdős–Rényi edge probability must be in [0, 1], got p={p}")
        return nx.gnp_random_graph(n, p, seed=seed)
    max_edges = n * (n - 1) // 2
    if not 0 <= int(m_edges) <= max_edges:
        raise ValueError(f"G(n, M) with n={n} holds 0..{max_edges} edges, got m_edges={m_edges}")
    return nx.gnm_random_graph(n, int(m_edges), seed=seed)


def _require(kw: dict[str, float], name: str, topology: str) -> float:
    if name not in kw:
        raise ValueError(f"topology '{topology}' needs parameter {name}")
    return kw[name]


def read_edge_list(path: str | Path, *, directed: bool = False) -> np.ndarray:
    """Read a graph from a text file of `i j` lines.

    Each line `i j` is an edge between nodes i and j: undirected by default (messages go
    both ways, `A[i, j] = A[j, i] = 1`), or with `directed` one edge from sender i to
    receiver j (`A[j, i] = 1`). A line holding one id `i` declares a node without edges.
    Node ids are 0-based integers and must be contiguous: the graph has `max id + 1`
    nodes, and every id below the largest must appear on some line (a gap is refused, as
    it is more often a typo or a 1-based file than a wanted isolated node; declare an
    isolated node on a line of its own). Blank lines and `#` comments are skipped;
    duplicate edges are merged. Ids may be separated by spaces, tabs or a comma.

    A third column is the edge's weight, as networkx's `write_weighted_edgelist` writes
    it. mpnode's graphs are unweighted (a dataset's adjacency holds 0 and 1,
    docs/dataset-format.md), so a weight must be 1 (the edge) or 0 (no edge; its ids still
    count as nodes); any other weight is refused rather than silently rounded.

    Args:
        path: the text file.
        directed: read `i j` as the one edge i → j instead of an undirected edge.

    Returns:
        uint8 `[n, n]`, zero diagonal; symmetric unless `directed`.

    Raises:
        ValueError: a malformed line, a negative id, a self-loop, a gap in the ids, or no
            edges at all.
    """
    pairs: list[tuple[int, int]] = []
    nodes: set[int] = set()
    for lineno, raw in enumerate(Path(path).read_text().splitlines(), start=1):
        line = raw.split("#", 1)[0].replace(",", " ").strip()
        if not line:
            continue
        fields = line.split()
        where = f"{path}:{lineno}"
        if len(fields) not in (1, 2, 3):
            raise ValueError(f"{where}: expected two node ids 'i j' and an optional weight "
                             f"(or one id, for a node without edges), got {raw.strip()!r}")
        weight = _weight(fields.pop(), where) if len(fields) == 3 else 1.0
        try:
            ids = [int(x) for x in fields]
        except ValueError:
            raise ValueError(f"{where}: node ids must be integers, got {raw.strip()!r}") from None
        if min(ids) < 0:
            raise ValueError(f"{where}: node ids are 0-based and non-negative, got "
                             f"{' '.join(fields)}")
        nodes.update(ids)
        if len(ids) == 1:
            continue
        if ids[0] == ids[1]:
            raise ValueError(f"{where}: self-loop {ids[0]} {ids[0]} is not allowed")
        if weight:
            pairs.append((ids[0], ids[1]))
    if not pairs:
        raise ValueError(f"{path}: no edges found (expected lines of 'i j')")
    n = max(nodes) + 1
    gaps = sorted(set(range(n)) - nodes)
    if gaps:
        shown = ", ".join(map(str, gaps[:5])) + (" ..." if len(gaps) > 5 else "")
        raise ValueError(f"{path}: node ids {shown} appear on no line, yet the largest id is "
                         f"{n - 1}; ids are 0-based and contiguous (list a node without edges "
                         "on a line of its own)")
    ij = np.asarray(pairs, dtype=np.int64)  # [E, 2], sender i, receiver j
    adjacency = np.zeros((n, n), dtype=np.uint8)
    adjacency[ij[:, 1], ij[:, 0]] = 1  # row j lists the senders of j
    if not directed:
        adjacency[ij[:, 0], ij[:, 1]] = 1
    return adjacency


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


def edges(adjacency: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Edge list of a graph, one entry per directed message.

    Args:
        adjacency: `[N, N]`, `A[i, j] != 0` iff j sends to i.

    Returns:
        `(senders, receivers)`, int64 `[E]` each, sorted by receiver then sender; an
        undirected edge appears once in each direction.
    """
    receivers, senders = np.nonzero(np.asarray(adjacency))
    return senders.astype(np.int64), receivers.astype(np.int64)
