"""The S¹ model: random graphs with power-law degrees and clustering from a hidden circle.

Serrano, Krioukov & Boguñá, "Self-similarity of complex networks and hidden metric spaces",
Phys. Rev. Lett. 100, 078701 (2008), in the form used by Laber, Eliassi-Rad & Klein,
arXiv:2602.08980 (2026). Each node i has an angle θ_i ~ U(0, 2π) on a circle of radius
R = N/(2π) (one node per unit of length) and a hidden degree κ_i drawn from the power law
P(κ) ∝ κ^(−γ) truncated at its natural cut-off κ_c = κ0 N^(1/(γ − 1)), the κ that N draws of
the untruncated law exceed once on average (N (κ0/κ_c)^(γ − 1) = 1; Boguñá, Pastor-Satorras &
Vespignani, Eur. Phys. J. B 38, 205 (2004)). Nodes i and j are joined, independently of every
other pair, with probability

    p_ij = 1 / (1 + (R Δθ_ij / (μ κ_i κ_j))^β),   μ = β sin(π/β) / (2π⟨k⟩),

where Δθ_ij = π − |π − |θ_i − θ_j|| is their angular distance. With this μ the expected
degree of node i is κ_i for large N (the integral of p_ij over the arc length is
2μκ_iκ_j (π/β)/sin(π/β)), so the degrees follow the power law of the κ's with exponent γ
(near 2: strong hubs) and mean E[κ], while β > 1 sets the clustering (larger: more).

Finite-size correction of κ0, the one networkx's `geometric_soft_configuration_graph` applies
(documented at
https://networkx.org/documentation/stable/reference/generated/networkx.generators.geometric.geometric_soft_configuration_graph.html),
derived here. On [κ0, κ_c] the truncated law has density
(γ − 1) κ0^(γ − 1) κ^(−γ) / (1 − 1/N), hence

    E[κ] = κ0 (γ − 1)/(γ − 2) · (1 − N^(−(γ − 2)/(γ − 1))) / (1 − 1/N),

and E[κ] = ⟨k⟩ exactly, at every N ≥ 2, for

    κ0 = ⟨k⟩ (γ − 2)/(γ − 1) · (1 − 1/N) / (1 − N^(−(γ − 2)/(γ − 1))).

The factor is 1.88 at γ = 2.1, N = 4096 (κ0 = 1.71, κ_c ≈ 3300) and → 1 as N → ∞ (slowly
near γ = 2); κ is drawn by inverting the truncated law's distribution function. Without the
cut-off and correction, the sample mean of κ (infinite variance for γ < 3) falls far below
⟨k⟩ at finite N: at γ = 2.1, ⟨k⟩ = 10 and N = 4096–8192 the mean degree was 2.4–5.3.

Realised mean degree, β = 2, ⟨k⟩ = 10: mean ± standard deviation per graph over seeds 0..63
(N = 1000), 0..23 (4096), 0..15 (8192), then in brackets the ensemble mean that the cut below
predicts (the average over θ and κ of the expected degree):

    γ = 2.1:  N = 1000: 8.18 ± 1.30 (8.12)   4096: 8.48 ± 0.74 (8.31)   8192: 8.38 ± 0.89 (8.38)
    γ = 2.5:  N = 1000: 9.61 ± 0.94 (9.55)   4096: 9.87 ± 0.47 (9.76)   8192: 9.78 ± 0.46 (9.82)
    γ = 3.5:  N = 1000: 9.95 ± 0.44 (9.91)   4096: 10.02 ± 0.20 (9.98)  8192: 9.96 ± 0.15 (9.99)

Near γ = 2 the mean degree still falls short of ⟨k⟩ although E[κ] = ⟨k⟩: the expected degree
of node i is κ_i only while μκ_iκ_j ≪ N/2. Averaged over θ, a pair contributes (β = 2)
2a·atan(N/(2a)), a = μκ_iκ_j, instead of πa: the arc is cut at N/2 and p_ij ≤ 1, so a pair
gives at most one edge however large κ_iκ_j. At γ = 2.1 a large share of E[κκ'] sits in pairs
with a ≳ N/2, and the cut costs, in the ensemble mean, 1.88 (N = 1000), 1.69 (4096) and 1.62
(8192) of the 10, i.e. 16–19 %, decaying only about as N^(−(γ − 2)) up to a logarithm (still
1.30 at N = 10⁶); at γ = 2.5 it costs 0.45, 0.24, 0.18 and at γ = 3.5 at most 0.09. This is
the model's own finite-size behaviour at the standard μ, which is kept (not re-fitted to hide
it). On top, the mean degree varies from graph to graph with the sample mean of the κ's: its
standard deviation is ≈ 1.2 at γ = 2.1, N = 1000 (√(4 Var_κ(E_κ'[2a·atan(N/(2a))])/N), the
leading term of this U-statistic's variance), 0.95 at 4096, 0.85 at 8192, against 0.38, 0.21,
0.16 at γ = 3.5.

Pure numpy: the N(N − 1)/2 pairs are drawn in blocks of rows, so memory stays
O(block · N + E), never an N × N matrix.
"""

from __future__ import annotations

import math
import operator

import numpy as np

# Pairs held at once (a block of rows × the columns right of it): float64 temporaries of
# 2**21 entries are 16 MiB each, small next to any graph worth this model.
_BLOCK_PAIRS = 2**21


def s1_hidden(n: int, seed: int, gamma: float,
              mean_degree: float) -> tuple[np.ndarray, np.ndarray]:
    """The hidden variables `s1_edges` draws for the same arguments.

    Args:
        n: number of nodes N, at least 1.
        seed: seed of `np.random.default_rng`.
        gamma: exponent γ > 2 of P(κ) ∝ κ^(−γ).
        mean_degree: ⟨k⟩ = E[κ], in (0, n − 1).

    Returns:
        `(theta, kappa)`, float64 `[n]` each: angles in [0, 2π) and hidden degrees in
        [κ0, κ_c) (module docstring).

    Raises:
        ValueError: parameters outside the ranges above.
    """
    _check(n, gamma, mean_degree)
    return _hidden(np.random.default_rng(seed), n, gamma, mean_degree)


def _hidden(rng: np.random.Generator, n: int, gamma: float,
            mean_degree: float) -> tuple[np.ndarray, np.ndarray]:
    """θ `[n]` then κ `[n]`, the first 2n draws of `rng` (κ by inverting the truncated law).

    P(κ ≤ x) = (1 − (κ0/x)^(γ − 1)) / (1 − 1/N) on [κ0, κ_c], so
    κ = κ0 (1 − U(1 − 1/N))^(−1/(γ − 1)) for U ~ U[0, 1): 1 − U(1 − 1/N) lies in (1/N, 1],
    hence κ0 ≤ κ < κ_c = κ0 N^(1/(γ − 1)).
    """
    theta = rng.uniform(0.0, 2.0 * math.pi, n)  # [n]
    kappa = _kappa0(n, gamma, mean_degree) * (
        1.0 - rng.random(n) * (1.0 - 1.0 / n)) ** (-1.0 / (gamma - 1.0))  # [n]
    return theta, kappa


def _kappa0(n: int, gamma: float, mean_degree: float) -> float:
    """κ0 giving the truncated law on [κ0, κ0 N^(1/(γ − 1))] the mean ⟨k⟩ (module docstring).

    ⟨k⟩ (γ − 2)/(γ − 1) · (1 − 1/N) / (1 − N^(−(γ − 2)/(γ − 1))), the last factor's
    denominator as −expm1 so that it stays accurate for γ near 2. Needs N ≥ 2.
    """
    a = (gamma - 2.0) / (gamma - 1.0)
    return mean_degree * a * (1.0 - 1.0 / n) / -math.expm1(-a * math.log(n))


def s1_edges(n: int, seed: int, gamma: float, beta: float, mean_degree: float, *,
             block_rows: int | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Draw an S¹ graph (module docstring) and return its messages.

    The seed fixes the graph: θ and κ are drawn first, then one uniform per pair (i, j),
    i < j, row after row, so the graph does not depend on `block_rows`.

    Args:
        n: number of nodes N, at least 1.
        seed: seed of `np.random.default_rng`.
        gamma: degree exponent γ > 2 (near 2: strong hubs).
        beta: β > 1; larger β, more clustering.
        mean_degree: ⟨k⟩ = E[κ], in (0, n − 1): the mean degree for large N (near γ = 2
            the graphs fall short of it at finite N, module docstring).
        block_rows: rows of pairs drawn at once (default: about 2**21 pairs a block).

    Returns:
        `(senders, receivers)`, int64 `[E]` each: every undirected edge once each way,
        no self-loops, no duplicates (not sorted).

    Raises:
        ValueError: parameters outside the ranges above.
    """
    _check(n, gamma, mean_degree, beta)
    rng = np.random.default_rng(seed)
    theta, kappa = _hidden(rng, n, gamma, mean_degree)
    mu = beta * math.sin(math.pi / beta) / (2.0 * math.pi * mean_degree)
    scale = n / (2.0 * math.pi) / mu  # R / μ
    rows = block_rows or max(1, _BLOCK_PAIRS // max(1, n))
    first, second = [], []
    for a in range(0, n - 1, rows):
        i, j = _block(rng, theta, kappa, scale, beta, a, min(a + rows, n - 1))
        first.append(i)
        second.append(j)
    i = np.concatenate(first) if first else np.zeros(0, np.int64)  # [E/2]
    j = np.concatenate(second) if second else np.zeros(0, np.int64)  # [E/2]
    return np.concatenate([i, j]), np.concatenate([j, i])


def _block(rng: np.random.Generator, theta: np.ndarray, kappa: np.ndarray, scale: float,
           beta: float, a: int, b: int) -> tuple[np.ndarray, np.ndarray]:
    """The edges (i, j), i < j, of rows a..b − 1: int64 `[E_block]` each.

    Works on the rectangle of rows a..b − 1 × columns a + 1..n − 1 and keeps its upper
    triangle j > i, row by row, which is the order the uniforms are drawn in.
    """
    n = len(theta)
    cols = np.arange(a + 1, n)  # [M]
    upper = cols[None, :] > np.arange(a, b)[:, None]  # [B, M]
    x = np.abs(theta[a:b, None] - theta[None, a + 1:])  # [B, M], |θ_i − θ_j| in [0, 2π)
    np.subtract(math.pi, x, out=x)
    np.abs(x, out=x)
    np.subtract(math.pi, x, out=x)  # Δθ_ij in [0, π]
    x *= (scale / kappa[a:b])[:, None]
    x /= kappa[None, a + 1:]  # R Δθ_ij / (μ κ_i κ_j)
    np.power(x, beta, out=x)
    x_upper = x[upper]  # [P], pairs j > i in row order
    u = rng.random(x_upper.size)  # [P]
    # u < p_ij = 1 / (1 + x^β), written without the division
    hit = u * (1.0 + x_upper) < 1.0  # [P]
    linked = np.zeros_like(upper)
    linked[upper] = hit
    r, c = np.nonzero(linked)
    return (r + a).astype(np.int64), cols[c].astype(np.int64)


def _check(n: int, gamma: float, mean_degree: float, beta: float = 2.0) -> None:
    """Raise ValueError unless n ≥ 1, γ > 2, 0 < ⟨k⟩ < n − 1 and β > 1 (all finite)."""
    try:
        n = operator.index(n)
    except TypeError:
        raise ValueError(f"the S¹ model needs an integer number of nodes, got n={n!r}") from None
    if n < 1:
        raise ValueError(f"a graph needs at least 1 node, got n={n}")
    if not (math.isfinite(gamma) and gamma > 2.0):
        raise ValueError(f"the S¹ model needs a finite degree exponent gamma > 2 (so that the "
                         f"mean degree is finite), got gamma={gamma}")
    if not (math.isfinite(beta) and beta > 1.0):
        raise ValueError(f"the S¹ model needs a finite beta > 1, got beta={beta}")
    if not (math.isfinite(mean_degree) and 0.0 < mean_degree < n - 1):
        raise ValueError(f"the S¹ model's mean_degree must lie strictly between 0 and "
                         f"n − 1 = {n - 1}, got mean_degree={mean_degree}")
