"""Graph topologies: complete, chain, Erdős–Rényi, Barabási–Albert, Watts–Strogatz and S¹,
as an adjacency matrix (`make_graph`) or an edge list (`make_edges`), in the convention of
`mpnode_cli.graphs.matrices` (`A[i, j] = 1` iff j sends to i; undirected, zero diagonal).

Random graphs come from networkx with an explicit integer seed, except `s1`, which
`mpnode_cli.graphs.s1` draws with numpy (`np.random.default_rng(seed)`), in blocks of node
pairs, so that neither networkx nor an N×N matrix is involved. The authors' graphs came
from LightGraphs.jl (MersenneTwister streams) and cannot be reproduced from Python, which
is why every dataset stores its adjacency (docs/systems.md).

networkx is imported inside the functions that need it, so that importing this module (and
the system registry, which imports it) stays cheap for the CLI.
"""

from __future__ import annotations

import math

import numpy as np

from mpnode_cli.graphs.matrices import DENSE_GRAPH_MAX_NODES, EdgeList
from mpnode_cli.graphs.s1 import s1_edges
from mpnode_cli.limits import MULTIPLICITY_MAX

TOPOLOGIES: tuple[str, ...] = ("complete", "chain", "er", "ba", "ws", "s1")

# Keyword arguments each topology accepts; anything else is a caller's mistake.
_KWARGS: dict[str, tuple[str, ...]] = {
    "complete": (),
    "chain": (),
    "er": ("p", "m_edges"),
    "ba": ("m",),
    "ws": ("k", "p"),
    "s1": ("gamma", "beta", "mean_degree"),
}


def make_graph(topology: str, n: int, seed: int, **kw: float) -> np.ndarray:
    """Build an undirected graph and return its adjacency matrix.

    Args:
        topology: one of `TOPOLOGIES`: `complete`; `chain` (path 0-1-...-n-1); `er`
            Erdős–Rényi, with `p` (G(n, p)) or `m_edges` (G(n, M), exactly M edges);
            `ba` Barabási–Albert with `m` edges per new node; `ws` Watts–Strogatz with
            ring degree `k` (k // 2 neighbours per side) and rewiring probability `p`;
            `s1` the S¹ model (Serrano, Krioukov & Boguñá, PRL 100, 078701 (2008);
            `mpnode_cli.graphs.s1`) with degree exponent `gamma` > 2, clustering `beta` > 1
            and mean hidden degree `mean_degree` = E[κ] in (0, n − 1) (near γ = 2 the
            mean degree falls short of it at finite n; see `mpnode_cli.graphs.s1`).
        n: number of nodes, at least 1.
        seed: seed of the random generators (ignored by deterministic topologies).
        **kw: the topology's parameters, as above.

    Returns:
        uint8 `[n, n]`, symmetric, zero diagonal.

    Raises:
        ValueError: unknown topology, missing/unexpected parameters, or parameters that
            the topology cannot satisfy at this size.
    """
    if topology == "s1":
        return _s1(n, seed, **kw).to_dense()
    import networkx as nx

    g = _nx_graph(topology, n, seed, **kw)
    return nx.to_numpy_array(g, nodelist=range(n), dtype=np.uint8)


def make_edges(topology: str, n: int, seed: int, **kw: float) -> EdgeList:
    """The graph `make_graph` builds, as an edge list, without an `[n, n]` matrix.

    The same topology, size, seed and parameters give the same graph as `make_graph`
    (networkx builds it either way, or `s1_edges` for `s1`); memory is O(n + E).

    Raises:
        ValueError: as `make_graph`.
    """
    if topology == "s1":
        return _s1(n, seed, **kw)
    g = _nx_graph(topology, n, seed, **kw)
    pairs = np.asarray(list(g.edges()), dtype=np.int64).reshape(-1, 2)  # [E_undirected, 2]
    return EdgeList.build(n, np.concatenate([pairs[:, 0], pairs[:, 1]]),
                          np.concatenate([pairs[:, 1], pairs[:, 0]]))


def expected_messages(topology: str, n: int, **kw: float) -> int:
    """The messages (directed edges, two per undirected edge) that `make_edges` builds for
    these arguments, before building it: exact for `complete`, `chain`, `ws`, `ba` and
    G(n, M); the mean for G(n, p) and `s1` (n · mean_degree).

    Raises:
        ValueError: as `make_graph`, for an unknown topology or a missing parameter.
    """
    _check_request(topology, n, kw)
    if topology == "complete":
        return n * (n - 1)
    if topology == "chain":
        return 2 * max(n - 1, 0)
    if topology == "er":
        if kw.get("m_edges") is not None:
            return 2 * int(kw["m_edges"])
        return math.ceil(float(_require(kw, "p", topology)) * n * (n - 1))
    if topology == "ba":  # networkx: a star of m edges, then m per node after the first m + 1
        m = int(_require(kw, "m", topology))
        return 2 * m * max(n - m, 0)
    if topology == "ws":
        return n * 2 * (int(_require(kw, "k", topology)) // 2)
    return math.ceil(n * float(_require(kw, "mean_degree", topology)))  # s1


def _s1(n: int, seed: int, **kw: float) -> EdgeList:
    """The `s1` graph of `make_graph`, drawn by `s1_edges` (arguments and errors as there)."""
    _check_request("s1", n, kw)
    gamma, beta, mean_degree = (float(_require(kw, name, "s1")) for name in _KWARGS["s1"])
    return EdgeList.build(n, *s1_edges(n, seed, gamma, beta, mean_degree))


def _check_request(topology: str, n: int, kw: dict[str, float]) -> None:
    """Raise ValueError for an unknown topology, parameters it does not take, or n < 1."""
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


def _nx_graph(topology: str, n: int, seed: int, **kw: float):
    """The networkx graph of `make_graph` (arguments and errors as there)."""
    import networkx as nx

    _check_request(topology, n, kw)
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
    return g


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


def join_hubs(graph: np.ndarray | EdgeList, hubs: int,
              multiplicity: int = 1) -> np.ndarray | EdgeList:
    """Degree coverage: `graph` with its `hubs` nodes of highest in-degree (the lowest
    index first among equals) joined to every other node, both ways, by `multiplicity`
    parallel edges each.

    Node models trained on small graphs meet hubs with more neighbours than any node they
    saw when run on larger ones (docs/transfer.md). A hub joined to all N − 1 others has the
    largest in-degree a graph of N nodes allows, so a pool of such graphs spans in-degrees
    up to N − 1 beside the topology's own. With `multiplicity` w > 1 the hub hears each
    other node w times (a multigraph: A[hub, j] = w), so its in-degree is w·(N − 1) and
    its neighbour sum that of a hub with w times as many neighbours, on the same N
    nodes; every other node hears the hub w times too. Symmetric graphs stay symmetric.

    Args:
        graph: uint8 `[N, N]` (`A[i, j]` the edges j → i) or an `EdgeList`.
        hubs: how many nodes to join to all others, 0 ≤ hubs ≤ N.
        multiplicity: the edges joining a hub to each other node, each way, 1–255; above
            1 only for a matrix (N ≤ `DENSE_GRAPH_MAX_NODES`).

    Returns:
        a new graph of the input's kind.

    Raises:
        ValueError: `hubs` outside 0..N, or `multiplicity` outside 1..255 or above 1 for
            an edge list.
    """
    dense = isinstance(graph, np.ndarray)
    n = graph.shape[0]
    if not 0 <= hubs <= n:
        raise ValueError(f"hubs must lie in 0..{n} (the graph's nodes), got {hubs}")
    if not 1 <= multiplicity <= MULTIPLICITY_MAX or (multiplicity > 1 and not dense):
        raise ValueError(f"hub multiplicity must lie in 1..{MULTIPLICITY_MAX}, and be 1 for "
                         f"graphs held as edge lists (above {DENSE_GRAPH_MAX_NODES} nodes); "
                         f"got {multiplicity} for {n} nodes")
    if hubs == 0:
        return graph
    degree = (graph != 0).sum(axis=1) if dense else np.bincount(graph.receivers, minlength=n)
    chosen = np.argsort(-degree, kind="stable")[:hubs]
    others = np.arange(n)
    senders = np.concatenate([np.repeat(chosen, n), np.tile(others, hubs)])
    receivers = np.concatenate([np.tile(others, hubs), np.repeat(chosen, n)])
    keep = senders != receivers
    senders, receivers = senders[keep], receivers[keep]
    if dense:
        out = graph.copy()
        out[receivers, senders] = multiplicity
        return out
    return EdgeList.build(n, np.concatenate([graph.senders, senders]),
                          np.concatenate([graph.receivers, receivers]))


def spread_multiplicity(w: int, graphs: int, g: int) -> int:
    """The parallel edges joining graph g's hubs (`generate --hub-multiplicity W`): W spread
    evenly from 1 (graph 0) to W (graph G − 1), so G graphs of N nodes span hub in-degrees
    N − 1 … W·(N − 1); W itself for one graph."""
    return w if graphs == 1 else 1 + round(g * (w - 1) / (graphs - 1))


def hubs_tag(hubs: int, w: int) -> str:
    """A generated file's default name's part for `--hubs H --hub-multiplicity W`."""
    return (f"-h{hubs}" if hubs else "") + (f"w{w}" if hubs and w > 1 else "")
