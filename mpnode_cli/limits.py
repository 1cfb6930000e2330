"""Limits shared by the configs (which must not import numpy, so that `--help` stays
fast) and by the code that enforces them: the graphs', the solver options'."""

# The largest graph held as an N×N matrix: stored as `graph/adjacency` in a dataset file
# (docs/dataset-format.md), given to systems as an ndarray and to models as a dense
# `[B, N, N]` batch. 256² = 65 536 entries, 64 KiB per uint8 graph: as small as the edge
# list of a graph of mean degree ≈ 4, and far below any memory concern.
DENSE_GRAPH_MAX_NODES = 256

# The most parallel edges between two nodes (`mpnode generate --hub-multiplicity`): a
# dataset's matrices are uint8.
MULTIPLICITY_MAX = 255

# What the dtypes mpnode computes in can hold (numpy's `finfo`, as numbers: the configs
# import no numpy): float32's largest finite value, and each dtype's machine epsilon.
FLOAT32_MAX = 3.4028234663852886e38
EPS = {"float32": 2.0**-23, "float64": 2.0**-52}
# The tightest rtol a solve in a dtype is allowed: below a few ulps of the states, a step's
# error estimate is rounding noise, and the step size shrinks towards the max_steps limit
# (an rtol of 1e-20 in float64 ran for minutes a trajectory).
RTOL_ULPS = 10


def within_float32(cls: type, value: float) -> float:
    """A pydantic field validator: refuse a number that float32 cannot hold."""
    if abs(value) > FLOAT32_MAX:
        raise ValueError(f"{value:g} is more than float32 holds (at most {FLOAT32_MAX:.4g})")
    return value
