"""What the verbs' configs share: seeds, the sample grid, each verb's solver defaults,
the parsing of the command line's lists, and a user's graph given as a file.

These check what can be checked without knowing the system (types, ranges, `dt` vs
`t_end`, the split).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from pathlib import Path
from typing import Any

from mpnode_cli.solver.options import SolverOptions

# Seeds are stored as HDF5 int64 attributes and fed to numpy and torch generators.
SEED_MAX = 2**63 - 1

# Relative slack when checking that t_end is a whole number of dt steps (0.3 / 0.1 is not
# exactly 3 in binary floating point).
_GRID_TOL = 1e-9
# The most dt steps in a horizon `0, dt, ..., t_end`: float64 holds every whole number up to
# 2⁵³, so beyond it "t_end is a whole number of dt steps" means nothing (and at inf, from a
# dt of 1e-300, nothing can be counted). Smaller horizons that would not fit in memory are
# refused by the memory estimates of generate and simulate, before anything is allocated.
MAX_STEPS = 2**53


def generate_solver() -> SolverOptions:
    """The solver of `mpnode generate`: ground truth at tight tolerances (float64)."""
    return SolverOptions(rtol=1e-8, atol=1e-10)


def train_solver() -> SolverOptions:
    """The solver of training rollouts: the paper's rtol = atol = 1e-4, with the integral
    step-size controller (fewer steps than PI at these tolerances: docs/solver.md), compiled
    for long runs (`mpnode_cli.training.recipe.resolve_compile`)."""
    return SolverOptions(rtol=1e-4, atol=1e-4, controller="i", compile="auto")


def over_defaults(defaults: Callable[[], SolverOptions], value: Any) -> Any:
    """A `solver` table that names only some options: the rest from the verb's defaults
    (not `SolverOptions`' own, which are `solve`'s)."""
    return {**defaults().model_dump(), **value} if isinstance(value, dict) else value


def split_fractions(cls: type, value: Any) -> Any:
    """Accept the command line's `"0.7,0.15,0.15"` as well as a list of three numbers."""
    parts = value.replace(" ", "").split(",") if isinstance(value, str) else value
    try:
        numbers = tuple(float(p) for p in parts)
    except (TypeError, ValueError):
        numbers = ()
    if len(numbers) != 3:
        raise ValueError(f"expected three fractions like 0.7,0.15,0.15, got {value!r}")
    return numbers


def valid_split(cls: type, value: tuple[float, float, float]) -> tuple[float, float, float]:
    if any(not 0.0 <= x <= 1.0 for x in value) or not math.isclose(sum(value), 1.0,
                                                                    abs_tol=1e-6):
        shown = ",".join(f"{x:g}" for x in value)
        raise ValueError(f"train,validation,test fractions must lie in [0, 1] and sum to 1, "
                         f"got {shown}")
    return value


def check_grid(dt: float, t_end: float) -> None:
    """Samples `0, dt, ..., t_end`: t_end must be a whole number of dt steps."""
    if dt > t_end:
        raise ValueError(f"dt ({dt:g}) is larger than t_end ({t_end:g})")
    steps = t_end / dt
    if not steps <= MAX_STEPS:  # also NaN and inf, which `round` cannot take
        raise ValueError(f"t_end / dt is {steps:.3g} steps, more than the 2**53 a horizon may "
                         "hold: lower t_end or raise dt")
    if abs(steps - round(steps)) > _GRID_TOL * max(1.0, steps):
        raise ValueError(f"t_end ({t_end:g}) must be a whole number of dt ({dt:g}) steps")


def check_graph_source(adjacency: Path | None, edge_list: Path | None, directed: bool) -> None:
    """A user's graph comes as exactly one of an adjacency array or an edge list."""
    if (adjacency is None) == (edge_list is None):
        raise ValueError("give the graph as exactly one of --adjacency A.npy or "
                         "--edge-list E.txt")
    if directed and edge_list is None:
        raise ValueError("directed applies to an edge list only (--edge-list); an "
                         "adjacency matrix says its own direction")


def name_list(cls: type, value: Any) -> Any:
    """Accept the command line's `"x,y"` as well as a list of names."""
    return [part.strip() for part in value.split(",")] if isinstance(value, str) else value


# A user's graph, as `import` and `simulate` take it (an adjacency array or an edge list),
# and `generate` an edge list.
ADJACENCY_HELP = ("Graph(s) as .npy: [N, N] for all trajectories or [K, N, N] one each; A_ij = 1 "
              "iff node j sends to node i.")
EDGE_LIST_HELP = ("Graph as a text file of 'i j' lines (optional weight column, 0 or 1), "
              "undirected unless --directed (docs/dataset-format.md).")
DIRECTED_HELP = "Read the edge list's 'i j' as one edge i → j."
